"""Locks shared by every process on one database: a PostgreSQL advisory lock; on SQLite (one
process by design) an in-process lock."""

from __future__ import annotations

import hashlib
import logging
import threading
from collections.abc import Iterator
from contextlib import contextmanager

from sqlalchemy import Engine, text

logger = logging.getLogger(__name__)

_local_locks: dict[str, threading.Lock] = {}
_local_guard = threading.Lock()


def advisory_key(name: str) -> int:
    """A stable signed 64-bit key for ``name`` (PostgreSQL advisory locks take a bigint)."""
    return int.from_bytes(
        hashlib.blake2b(name.encode(), digest_size=8).digest(), "big", signed=True
    )


@contextmanager
def exclusive(engine: Engine, name: str, wait: bool = False) -> Iterator[bool]:
    """Hold the lock ``name`` across processes while the block runs: yields True when held;
    without ``wait``, False at once when another holder has it (the block should then skip
    its work); with ``wait``, True once the other holder has released it.

    PostgreSQL: a session-level advisory lock (``pg_advisory_lock``, or
    ``pg_try_advisory_lock`` without ``wait``) on a connection kept for the block (the block
    may run many transactions on other connections), released by ``pg_advisory_unlock``, or by
    the server if the process dies. Other databases: a lock of this process.
    """
    if engine.dialect.name == "postgresql":
        key = advisory_key(name)
        with engine.connect() as conn:
            if wait:
                conn.execute(text("SELECT pg_advisory_lock(:k)"), {"k": key})
                held = True
            else:
                held = bool(conn.scalar(text("SELECT pg_try_advisory_lock(:k)"), {"k": key}))
            conn.commit()
            try:
                yield held
            finally:
                if held:
                    conn.scalar(text("SELECT pg_advisory_unlock(:k)"), {"k": key})
                    conn.commit()
        return
    with _local_guard:
        lock = _local_locks.setdefault(name, threading.Lock())
    held = lock.acquire(blocking=wait)
    try:
        yield held
    finally:
        if held:
            lock.release()
