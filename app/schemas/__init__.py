"""Pydantic request/response models of the v1 API (never ORM objects)."""
