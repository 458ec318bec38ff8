"""Admission control for the requests that run the engine (localize, add): a bounded number
compute at once, a bounded number wait, the rest are refused at once."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

from app.errors import ProblemError
from services.runtime.worker_slots import WorkerSlots

RETRY_AFTER_S = 1


class Admission:
    """``slots.workers`` requests compute at once (``slots``, held around engine work, with
    their memory) and at most ``queued`` more wait for a slot; a request beyond that is
    refused without waiting.

    Attributes:
        slots: held while a request runs the engine.
    """

    def __init__(self, slots: WorkerSlots, queued: int) -> None:
        self.slots = slots
        self.workers = slots.workers
        self._capacity = slots.workers + queued
        self._admitted = 0
        self._lock = threading.Lock()

    @property
    def capacity(self) -> int:
        """Requests that may be admitted at once (computing or waiting)."""
        return self._capacity

    @property
    def admitted(self) -> int:
        """Requests admitted now: computing, waiting for a worker, or reading the database
        before or after their engine work."""
        with self._lock:
            return self._admitted

    @contextmanager
    def admit(self) -> Iterator[None]:
        """Counts the request in while the block runs.

        Raises:
            ProblemError: 503 with ``Retry-After`` when every worker is busy and the queue is
                full.
        """
        with self._lock:
            if self._admitted >= self._capacity:
                raise ProblemError(
                    503,
                    "service-busy",
                    "Service busy",
                    f"{self._capacity} localize or add requests are in progress or waiting; "
                    f"retry after {RETRY_AFTER_S} s",
                    headers={"Retry-After": str(RETRY_AFTER_S)},
                )
            self._admitted += 1
        try:
            yield
        finally:
            with self._lock:
                self._admitted -= 1
