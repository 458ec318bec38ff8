"""Run alembic migrations programmatically (``slloc db upgrade``, app start-up, tests)."""

from __future__ import annotations

import threading
from pathlib import Path

from alembic import command
from alembic.config import Config
from sqlalchemy import Connection, Engine, text

MIGRATIONS_DIR = Path(__file__).parent / "migrations"

# alembic keeps the running migration in module globals: one upgrade per process at a time
_IN_PROCESS = threading.Lock()
# any constant both sides agree on: the key of the PostgreSQL advisory lock of upgrades
_ADVISORY_KEY = 0x736C6C6F63  # "slloc"


def upgrade(engine: Engine, revision: str = "head") -> None:
    """Bring the schema of ``engine``'s database to ``revision``. Concurrent upgrades of one
    database (two imports, two server workers starting) run one after the other; the later
    finds the schema current."""
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    with _IN_PROCESS, engine.begin() as connection:
        _lock_schema(connection)
        config.attributes["connection"] = connection
        command.upgrade(config, revision)


def _lock_schema(connection: Connection) -> None:
    """Hold the database's schema lock until ``connection``'s transaction ends: a
    transaction-scoped advisory lock on PostgreSQL, the write lock on SQLite."""
    if connection.dialect.name == "postgresql":
        connection.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": _ADVISORY_KEY})
    elif connection.dialect.name == "sqlite":
        connection.exec_driver_sql("BEGIN IMMEDIATE")
