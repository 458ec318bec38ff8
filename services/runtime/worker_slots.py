"""The localize workers' slots and the memory the requests computing on them hold together.

Every request that runs the engine holds a worker slot while it computes (the thread plan
sizes slots × threads per operation to the cores) and, with it, the memory its shape needs
(``services.runtime.memory.request_memory_mib``) out of a budget the memory bound counts
once (``SLLOC_COMPUTING_MEMORY_MIB``). A request whose share does not fit beside those
computing waits, first come first served: small requests compute on every worker at once, a
request at the limits computes beside small ones or alone, and their sum never passes the
budget. A request estimated above the whole budget waits until it can hold all of it.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext


class WorkerSlots:
    """``workers`` slots and ``memory_mib`` MiB for the requests computing at once.

    Attributes:
        semaphore: the slots; idle ones are lent through it (``SpareWorkers``).
    """

    def __init__(self, workers: int, memory_mib: float) -> None:
        if workers < 1 or memory_mib <= 0:
            raise ValueError(f"need workers >= 1 and memory_mib > 0, got {workers}, {memory_mib}")
        self.semaphore = threading.BoundedSemaphore(workers)
        self.workers = workers
        self.memory_mib = memory_mib
        self._held_mib = 0.0
        self._waiting: deque[object] = deque()
        self._changed = threading.Condition()

    @property
    def held_mib(self) -> float:
        """The memory the requests computing now hold."""
        with self._changed:
            return self._held_mib

    @property
    def waiting(self) -> int:
        """Requests holding a slot and waiting for memory."""
        with self._changed:
            return len(self._waiting)

    @contextmanager
    def hold(self, mib: float) -> Iterator[None]:
        """Holds a slot and ``mib`` of the memory (at most all of it) while the block runs;
        waits for both, the memory in the order the requests asked for it."""
        share = min(max(mib, 0.0), self.memory_mib)
        with self.semaphore:
            self._reserve(share)
            try:
                yield
            finally:
                with self._changed:
                    self._held_mib -= share
                    self._changed.notify_all()

    def _reserve(self, share: float) -> None:
        turn = object()
        with self._changed:
            self._waiting.append(turn)
            while self._waiting[0] is not turn or self._held_mib + share > self.memory_mib:
                self._changed.wait()
            self._waiting.popleft()
            self._held_mib += share
            self._changed.notify_all()  # the next in line may fit as well


def holding(slots: WorkerSlots | None, mib: float) -> AbstractContextManager[None]:
    """``slots.hold(mib)``; nothing to hold without slots (the engine used alone)."""
    return nullcontext() if slots is None else slots.hold(mib)
