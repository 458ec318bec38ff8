"""Use cases shared by the HTTP routes, the CLI and the in-process evaluator.

They raise domain errors (``app.usecases.errors``, ``services.errors``) and return domain
values; ``app.errors`` turns the errors into problem documents and the routes turn the values
into response schemas.
"""
