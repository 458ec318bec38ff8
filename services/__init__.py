"""The slloc engine: geometry, features, retrieval, estimators and the localization pipeline.

Nothing in this package knows about HTTP or SQL.
"""
