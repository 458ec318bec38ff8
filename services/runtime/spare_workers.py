"""Idle localize workers lent to a computing request.

Every request that computes holds one worker slot (the thread plan sizes slots × threads per
operation to the cores). Work that splits over references, matching the query with each, may
borrow the slots that are free at that moment and run its parts at once on them; the borrowed
slots go back when that work ends. A request alone on the machine then uses every core, while
concurrent requests find no slot free and keep one worker each: threads never exceed the plan.
A request arriving meanwhile waits for the borrowed slot at most one split's duration.
Work that cannot be split but can run one operation on more threads (a network's forward
pass) borrows every lendable slot or none (``borrow_all``).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from contextlib import contextmanager
from typing import Protocol, TypeVar

Item = TypeVar("Item")
Result = TypeVar("Result")


class Spread(Protocol):
    """Runs ``work(items)``, possibly as contiguous runs of ``items`` on several threads at
    once, and joins the results in order (``SpareWorkers.split``)."""

    def __call__(
        self, work: Callable[[Sequence[Item]], list[Result]], items: Sequence[Item]
    ) -> list[Result]: ...


class SpareWorkers:
    """Lends the free slots of ``slots`` (the workers' semaphore, also held by each computing
    request), at most ``most`` at a time, with a thread for each."""

    def __init__(self, slots: threading.Semaphore, most: int) -> None:
        if most < 0:
            raise ValueError(f"most must be at least 0, got {most}")
        self._slots = slots
        self.most = most
        self._pool = (
            ThreadPoolExecutor(max_workers=most, thread_name_prefix="spare-worker")
            if most
            else None
        )

    @contextmanager
    def borrow(self, wanted: int | None = None) -> Iterator[int]:
        """Takes the slots free now, at most ``wanted`` (None: ``most``), never waiting, and
        yields how many; gives them back after."""
        limit = self.most if wanted is None else min(self.most, wanted)
        taken = 0
        try:
            while taken < limit and self._slots.acquire(blocking=False):
                taken += 1
            yield taken
        finally:
            for _ in range(taken):
                self._slots.release()

    @contextmanager
    def borrow_all(self) -> Iterator[bool]:
        """Takes all ``most`` lendable slots when every one is free now, never waiting, and
        yields True; otherwise takes none and yields False. Gives them back after."""
        with self.borrow() as taken:
            if 0 < taken == self.most:
                yield True
                return
        yield False  # some slot is busy: holding the others would only block

    def split(
        self, work: Callable[[Sequence[Item]], list[Result]], items: Sequence[Item]
    ) -> list[Result]:
        """``work(items)``, with ``items`` cut into contiguous runs of about equal length, one
        for the caller and one for each borrowed slot, run at once. ``work`` may return fewer
        results than it was given items (it was stopped); the list then ends after the first
        run that did. The slots go back only once every run has ended, raised or not."""
        if self._pool is None or len(items) < 2:
            return work(items)
        with self.borrow(len(items) - 1) as extra:
            if not extra:
                return work(items)
            runs = _cut(items, 1 + extra)
            others = [self._pool.submit(work, run) for run in runs[1:]]
            try:
                first = work(runs[0])
            finally:
                wait(others)
            done = [first] + [future.result() for future in others]
        out: list[Result] = []
        for run, results in zip(runs, done, strict=True):
            out.extend(results)
            if len(results) < len(run):
                break
        return out

    def shutdown(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)


def _cut(items: Sequence[Item], parts: int) -> list[Sequence[Item]]:
    """``items`` in at most ``parts`` contiguous, non-empty runs whose lengths differ by at
    most one."""
    parts = max(1, min(parts, len(items)))
    size, longer = divmod(len(items), parts)
    runs, start = [], 0
    for i in range(parts):
        end = start + size + (1 if i < longer else 0)
        runs.append(items[start:end])
        start = end
    return runs
