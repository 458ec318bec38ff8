"""The thread policy: how many localize requests compute at once and how many threads each
operation inside one may use (onnxruntime intra-op, OpenCV, BLAS / OpenMP), sized together
from the usable cores so that workers × threads per operation never exceeds them.

On two cores, a second thread per operation while another request computes costs more than
it gives (ALIKED's ONNX graph: 887 ms on one thread, 1114 ms on two under load; XFeat's torch
forward 38 ms on one, 1065 ms on two), so the default gives each worker its share of cores.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import cv2
from threadpoolctl import threadpool_limits

logger = logging.getLogger(__name__)

# concurrent localize requests at most by default: more only queue for the same cores and
# each holds its own buffers
MAX_DEFAULT_WORKERS = 4


@dataclass(frozen=True)
class ThreadPlan:
    """cores: the cores the process may use. workers: localize / add requests that compute at
    once. threads_per_worker: threads one operation of a request may use (onnxruntime
    intra-op, OpenCV, BLAS / OpenMP)."""

    cores: int
    workers: int
    threads_per_worker: int

    @property
    def oversubscribed(self) -> bool:
        """More threads may run at once than there are cores (only when both were set)."""
        return self.workers * self.threads_per_worker > self.cores


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def plan_threads(
    cores: int | None = None, workers: int | None = None, threads_per_worker: int | None = None
) -> ThreadPlan:
    """The plan for ``cores`` (None: the usable cores); ``workers`` and ``threads_per_worker``
    override the defaults: workers = min(cores, 4), threads = cores // workers (at least 1).

    Raises:
        ValueError: a count below 1.
    """
    cores = usable_cores() if cores is None else cores
    for name, value in (("cores", cores), ("workers", workers), ("threads", threads_per_worker)):
        if value is not None and value < 1:
            raise ValueError(f"{name} must be at least 1, got {value}")
    if workers is None:
        workers = min(cores, MAX_DEFAULT_WORKERS)
        if threads_per_worker is not None:
            workers = max(1, min(workers, cores // threads_per_worker))
    if threads_per_worker is None:
        threads_per_worker = max(1, cores // workers)
    return ThreadPlan(cores, workers, threads_per_worker)


def apply_thread_plan(plan: ThreadPlan) -> None:
    """Limits OpenCV's and the BLAS / OpenMP libraries' threads in this process to
    ``plan.threads_per_worker`` (onnxruntime sessions take it from ``OnnxOptions``)."""
    if plan.oversubscribed:
        logger.warning(
            "threads: %d workers × %d threads per operation exceed the %d usable cores; "
            "requests will slow each other down",
            plan.workers,
            plan.threads_per_worker,
            plan.cores,
        )
    cv2.setNumThreads(plan.threads_per_worker)
    threadpool_limits(plan.threads_per_worker)
    logger.info(
        "threads: %d cores, %d localize workers × %d threads per operation",
        plan.cores,
        plan.workers,
        plan.threads_per_worker,
    )


_opencv_threads_lock = threading.Lock()


@contextmanager
def opencv_threads(threads: int) -> Iterator[None]:
    """OpenCV's threads set to ``threads`` for the block, then set back. The setting is the
    process's: hold every worker slot meanwhile (``SpareWorkers.borrow_all``) so that no other
    request computes. An OpenCV call that starts on another thread while the block's runs
    on its threads runs on its own thread alone (OpenCV runs one parallel region at a time)."""
    with _opencv_threads_lock:
        before = cv2.getNumThreads()
        cv2.setNumThreads(threads)
        try:
            yield
        finally:
            cv2.setNumThreads(before)
