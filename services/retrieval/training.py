"""Runs training off the request path (VLAD vocabularies, approximate retrieval indexes): one
background worker at the lowest CPU priority, so requests running meanwhile keep their speed,
and one pending job per key, so a burst of adds that crosses a threshold trains once."""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable, Hashable
from concurrent.futures import Future, ThreadPoolExecutor

logger = logging.getLogger(__name__)


class BackgroundTrainer:
    """Schedules training jobs on one worker thread; a job already pending or running for the
    same key is not scheduled twice. Failures are logged, never raised into a request."""

    def __init__(self, name: str = "vocabulary") -> None:
        """``name``: what the jobs train, for the worker thread's name and the logs."""
        self.name = name
        self._executor = ThreadPoolExecutor(
            max_workers=1, thread_name_prefix=name.replace(" ", "-"), initializer=_lowest_priority
        )
        self._pending: dict[Hashable, Future[None]] = {}
        self._lock = threading.Lock()

    def schedule(self, key: Hashable, job: Callable[[], object]) -> bool:
        """Run ``job`` in the background unless one for ``key`` is pending; True when queued."""
        with self._lock:
            if key in self._pending:
                return False
            self._pending[key] = self._executor.submit(self._run, key, job)
            return True

    def _run(self, key: Hashable, job: Callable[[], object]) -> None:
        try:
            job()
        except Exception:
            logger.exception("background %s training for %s failed", self.name, key)
        finally:
            with self._lock:
                self._pending.pop(key, None)

    def pending(self) -> int:
        """Jobs queued or running."""
        with self._lock:
            return len(self._pending)

    def wait(self, timeout: float | None = None) -> None:
        """Block until every job scheduled so far has finished (tests, tools, shutdown)."""
        with self._lock:
            futures = list(self._pending.values())
        for future in futures:
            future.result(timeout)

    def shutdown(self) -> None:
        self._executor.shutdown(wait=True, cancel_futures=True)


def _lowest_priority() -> None:
    """Give the calling thread the lowest scheduling priority (Linux schedules threads as
    tasks; elsewhere the thread keeps its priority)."""
    if hasattr(os, "setpriority"):
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
        except OSError:
            logger.info("could not lower a background trainer's priority")
