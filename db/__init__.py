"""Persistence: SQLAlchemy 2.0 models, engine/session, repositories and alembic migrations."""
