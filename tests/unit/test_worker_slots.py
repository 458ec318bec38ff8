"""The workers' slots and the memory the requests computing on them hold together
(``services/runtime/worker_slots.py``): the sum never passes the budget, small requests
compute at once, a large one alone, in the order they asked."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import pytest

from services.runtime.worker_slots import WorkerSlots, holding


def _run_all(slots: WorkerSlots, shares: list[float], hold_s: float = 0.05) -> list[float]:
    """Runs one thread per share, each holding it for ``hold_s``; returns the largest memory
    held at once as seen from inside the requests, and checks each never saw more than the
    budget."""
    seen: list[float] = []
    lock = threading.Lock()

    def request(mib: float) -> None:
        with slots.hold(mib):
            with lock:
                seen.append(slots.held_mib)
            time.sleep(hold_s)

    threads = [threading.Thread(target=request, args=(mib,)) for mib in shares]
    for thread in threads:
        thread.start()
        time.sleep(0.005)  # they ask in order
    for thread in threads:
        thread.join(timeout=10)
    assert not any(thread.is_alive() for thread in threads)
    return seen


def test_small_requests_compute_at_once_within_the_budget() -> None:
    slots = WorkerSlots(workers=2, memory_mib=700.0)
    seen = _run_all(slots, [200.0, 200.0, 200.0, 200.0])
    assert max(seen) == pytest.approx(400.0)  # two at once: the workers, not the memory, bind
    assert slots.held_mib == 0.0 and slots.waiting == 0


def test_a_large_request_computes_alone() -> None:
    slots = WorkerSlots(workers=2, memory_mib=700.0)
    order: list[str] = []
    running = threading.Semaphore(0)
    release = threading.Event()

    def small() -> None:
        with slots.hold(200.0):
            order.append("small")
            running.release()
            release.wait(5)

    def large() -> None:
        with slots.hold(600.0):
            order.append(f"large with {slots.held_mib:.0f} held")

    first = threading.Thread(target=small)
    first.start()
    assert running.acquire(timeout=5)
    second = threading.Thread(target=large)
    second.start()
    time.sleep(0.1)
    assert order == ["small"] and slots.waiting == 1  # it waits for the small one's memory
    release.set()
    first.join(5)
    second.join(5)
    assert order == ["small", "large with 600 held"]


def test_memory_goes_in_the_order_it_was_asked_for() -> None:
    """A large request waiting is not overtaken by small ones that would fit: it does not
    starve behind a stream of them."""
    slots = WorkerSlots(workers=3, memory_mib=700.0)
    order: list[str] = []
    release = threading.Event()
    started = threading.Semaphore(0)

    def request(name: str, mib: float, wait: Callable[[], object] = lambda: None) -> None:
        with slots.hold(mib):
            order.append(name)
            started.release()
            wait()

    first = threading.Thread(target=request, args=("small 1", 200.0, lambda: release.wait(5)))
    first.start()
    assert started.acquire(timeout=5)
    large = threading.Thread(target=request, args=("large", 600.0))
    large.start()
    time.sleep(0.05)
    late = threading.Thread(target=request, args=("small 2", 200.0))
    late.start()
    time.sleep(0.1)
    assert order == ["small 1"]  # "small 2" would fit beside "small 1" but is behind "large"
    release.set()
    for thread in (first, large, late):
        thread.join(5)
    assert order == ["small 1", "large", "small 2"]


def test_a_request_above_the_budget_holds_all_of_it() -> None:
    slots = WorkerSlots(workers=2, memory_mib=500.0)
    seen = _run_all(slots, [900.0, 100.0])
    assert seen == [500.0, 100.0]


def test_the_slots_bound_the_requests_as_well() -> None:
    slots = WorkerSlots(workers=1, memory_mib=1000.0)
    seen = _run_all(slots, [10.0, 10.0, 10.0])
    assert max(seen) == 10.0


def test_a_request_that_raises_gives_its_memory_back() -> None:
    slots = WorkerSlots(workers=2, memory_mib=100.0)
    with pytest.raises(RuntimeError), slots.hold(80.0):
        raise RuntimeError("engine failed")
    assert slots.held_mib == 0.0
    assert slots.semaphore.acquire(blocking=False) and slots.semaphore.acquire(blocking=False)


def test_holding_without_slots_holds_nothing() -> None:
    with holding(None, 1e9):
        pass


@pytest.mark.parametrize(("workers", "memory"), [(0, 100.0), (1, 0.0)])
def test_invalid_budgets_are_refused(workers: int, memory: float) -> None:
    with pytest.raises(ValueError, match="workers"):
        WorkerSlots(workers, memory)
