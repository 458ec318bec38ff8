"""Locks shared by every process on one database: a PostgreSQL advisory lock; on SQLite (one
process by design) an in-process lock."""

from __future__ import annotations

import hashlib
import logging
import threading
import time
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


# seconds between two tries of a PostgreSQL advisory lock while waiting for it
POLL_S = 0.1


@contextmanager
def exclusive(engine: Engine, name: str, wait_s: float = 0.0) -> Iterator[bool]:
    """Hold the lock ``name`` across processes while the block runs: yields True when held,
    False when another holder kept it for ``wait_s`` seconds (0: tried once; the block should
    then skip its work).

    PostgreSQL: a session-level advisory lock (``pg_try_advisory_lock``, tried every
    ``POLL_S`` until ``wait_s`` has passed) on a connection kept for the block (the block may
    run many transactions on other connections), released by ``pg_advisory_unlock``, or by
    the server if the process dies. Other databases: a lock of this process.
    """
    if engine.dialect.name == "postgresql":
        key = advisory_key(name)
        deadline = time.monotonic() + wait_s
        with engine.connect() as conn:
            while True:
                held = bool(conn.scalar(text("SELECT pg_try_advisory_lock(:k)"), {"k": key}))
                conn.commit()
                if held or time.monotonic() >= deadline:
                    break
                time.sleep(min(POLL_S, max(0.0, deadline - time.monotonic())))
            try:
                yield held
            finally:
                if held:
                    conn.scalar(text("SELECT pg_advisory_unlock(:k)"), {"k": key})
                    conn.commit()
        return
    with _local_guard:
        lock = _local_locks.setdefault(name, threading.Lock())
    held = lock.acquire(timeout=wait_s)  # 0: a single try
    try:
        yield held
    finally:
        if held:
            lock.release()
