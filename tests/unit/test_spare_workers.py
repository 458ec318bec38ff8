"""Idle worker slots lent to a request's matching and extraction: only the free ones, given
back after, the results in order (issue #13)."""

from __future__ import annotations

import threading
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
import pytest

from services.features.base import LocalFeatures
from services.features.keypoint_onnx import OnnxKeypointExtractor, ResizeOptions
from services.matching.nearest_neighbor import NearestNeighborMatcher
from services.runtime import spare_workers
from services.runtime.spare_workers import SpareWorkers


@pytest.fixture
def slots() -> threading.BoundedSemaphore:
    return threading.BoundedSemaphore(3)


@pytest.fixture
def spare(slots: threading.BoundedSemaphore) -> Iterator[SpareWorkers]:
    workers = SpareWorkers(slots, most=2)
    yield workers
    workers.shutdown()


def _free(slots: threading.BoundedSemaphore) -> int:
    taken = 0
    while slots.acquire(blocking=False):
        taken += 1
    for _ in range(taken):
        slots.release()
    return taken


def test_borrows_only_free_slots_and_gives_them_back(
    slots: threading.BoundedSemaphore, spare: SpareWorkers
) -> None:
    slots.acquire()  # the request itself
    with spare.borrow() as lent:
        assert lent == 2
        assert _free(slots) == 0
    assert _free(slots) == 2
    slots.acquire()  # a second request computing
    with spare.borrow() as lent:
        assert lent == 1
    with spare.borrow() as lent, spare.borrow() as more:
        assert (lent, more) == (1, 0)
    assert _free(slots) == 1
    with spare.borrow(wanted=0) as lent:
        assert lent == 0 and _free(slots) == 1


def test_borrow_all_takes_every_lendable_slot_or_none(
    slots: threading.BoundedSemaphore, spare: SpareWorkers
) -> None:
    slots.acquire()  # the request itself
    with spare.borrow_all() as wide:
        assert wide and _free(slots) == 0
    assert _free(slots) == 2
    slots.acquire()  # a second request computing: one slot free, not enough
    with spare.borrow_all() as wide:
        assert not wide and _free(slots) == 1  # the free slot is not held meanwhile
    slots.release()
    with pytest.raises(RuntimeError, match="boom"), spare.borrow_all():
        raise RuntimeError("boom")
    assert _free(slots) == 2
    alone = SpareWorkers(slots, most=0)
    with alone.borrow_all() as wide:
        assert not wide


class _Session:
    """An extractor session that counts its runs (no detections)."""

    def __init__(self) -> None:
        self.runs = 0

    def run(self, _: object, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        self.runs += 1
        return [np.zeros((4, 2), np.float32), np.full(4, -np.inf, np.float32), np.zeros((4, 8))]


def test_extraction_runs_the_wide_session_only_on_every_idle_worker(
    slots: threading.BoundedSemaphore, spare: SpareWorkers
) -> None:
    narrow, wide = _Session(), _Session()
    extractor = OnnxKeypointExtractor(narrow, "x", 4, ResizeOptions(4, 64), wide_session=wide)
    image = np.zeros((64, 64, 3), np.uint8)
    slots.acquire()  # the request itself
    extractor.extract(image, spare)
    assert (narrow.runs, wide.runs) == (0, 1)
    extractor.with_budget(2, None).extract(image, spare)  # a map's budget keeps both sessions
    assert (narrow.runs, wide.runs) == (0, 2)
    slots.acquire()  # another request computing
    extractor.extract(image, spare)
    extractor.extract(image)  # nothing lent
    assert (narrow.runs, wide.runs) == (2, 2)
    assert _free(slots) == 1


def test_slots_come_back_when_the_work_raises(
    slots: threading.BoundedSemaphore, spare: SpareWorkers
) -> None:
    def fails(items: Sequence[int]) -> list[int]:
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        spare.split(fails, list(range(10)))
    assert _free(slots) == 3


class _WatchedSlots(threading.BoundedSemaphore):
    """Worker slots that record, each time one is given back, which borrowed runs had ended,
    and set ``given_back``."""

    def __init__(self, value: int, ended: list[int], given_back: threading.Event) -> None:
        super().__init__(value)
        self._ended = ended
        self._given_back = given_back
        self.ended_at_release: list[list[int]] = []

    def release(self, n: int = 1) -> None:
        self.ended_at_release.append(sorted(self._ended))
        self._given_back.set()
        super().release(n)


def test_slots_come_back_only_after_every_run_ended(monkeypatch: pytest.MonkeyPatch) -> None:
    # The borrowed runs end only once the split has gone past the caller's failure, to
    # waiting for them or to giving their slots back (the bug), whichever it does first.
    moved_on = threading.Event()
    ended: list[int] = []
    slots = _WatchedSlots(3, ended, given_back=moved_on)
    spare = SpareWorkers(slots, most=2)
    real_wait = spare_workers.wait

    def wait_for_runs(*args: Any, **kwargs: Any) -> Any:
        moved_on.set()
        return real_wait(*args, **kwargs)

    monkeypatch.setattr(spare_workers, "wait", wait_for_runs)

    def caller_run_fails_fast(items: Sequence[int]) -> list[int]:
        if items[0] == 0:
            raise RuntimeError("boom")
        assert moved_on.wait(10)
        ended.append(items[0])
        return list(items)

    try:
        with pytest.raises(RuntimeError, match="boom"):
            spare.split(caller_run_fails_fast, list(range(9)))
        # both borrowed runs had ended when their slots went back
        assert slots.ended_at_release == [[3, 6], [3, 6]]
        assert _free(slots) == 3
    finally:
        spare.shutdown()


def test_a_single_item_borrows_nothing(
    slots: threading.BoundedSemaphore, spare: SpareWorkers
) -> None:
    seen: list[int] = []

    def record(items: Sequence[int]) -> list[int]:
        seen.append(_free(slots))
        return list(items)

    assert spare.split(record, [7]) == [7]
    assert seen == [3]


@pytest.mark.parametrize("count", [0, 1, 2, 3, 10])
def test_split_runs_at_once_and_keeps_the_order(spare: SpareWorkers, count: int) -> None:
    # every run waits until all have started: the split finishes only if they run at once
    together = threading.Barrier(max(1, min(count, 3)), timeout=10)
    threads: set[int] = set()

    def square(items: Sequence[int]) -> list[int]:
        threads.add(threading.get_ident())
        together.wait()
        return [i * i for i in items]

    assert spare.split(square, list(range(count))) == [i * i for i in range(count)]
    assert len(threads) == together.parties


def test_split_ends_after_a_stopped_run(spare: SpareWorkers) -> None:
    def second_run_stops(items: Sequence[int]) -> list[int]:
        return list(items[:1]) if items[0] == 4 else list(items)

    # runs [0..3], [4..6], [7..9]: the second stops after its first item
    assert spare.split(second_run_stops, list(range(10))) == [0, 1, 2, 3, 4]


def test_no_slot_free_runs_on_the_caller(slots: threading.BoundedSemaphore) -> None:
    spare = SpareWorkers(slots, most=0)
    caller = threading.get_ident()
    seen: list[int] = []

    def record(items: Sequence[int]) -> list[int]:
        seen.append(threading.get_ident())
        return list(items)

    assert spare.split(record, [1, 2, 3]) == [1, 2, 3]
    assert seen == [caller]
    with pytest.raises(ValueError, match="at least 0"):
        SpareWorkers(slots, most=-1)


def test_matching_spread_equals_matching_alone(spare: SpareWorkers) -> None:
    rng = np.random.default_rng(0)

    def features(n: int) -> LocalFeatures:
        d = rng.normal(size=(n, 64)).astype(np.float32)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        xy = rng.uniform(0, 100, size=(n, 2)).astype(np.float32)
        return LocalFeatures(xy, d, np.ones(n, np.float32), (100, 100))

    query = features(300)
    # references share part of the query's descriptors, so each has matches of its own
    references = []
    for k in range(7):
        ref = features(250)
        ref.descriptors[: 20 * (k + 1)] = query.descriptors[k : k + 20 * (k + 1)]
        references.append(ref)
    matcher = NearestNeighborMatcher(0.9, min_similarity=0.9)  # random pairs: cosine < 0.6
    alone = matcher.match_many(query, references)
    spread = matcher.match_many(query, references, spread=spare.split)
    assert [len(m) for m in alone] == [20 * (k + 1) for k in range(7)]
    assert len(spread) == len(alone)
    for a, b in zip(alone, spread, strict=True):
        np.testing.assert_array_equal(a, b)
