"""The thread policy: workers × threads per operation within the cores (issue #13)."""

from __future__ import annotations

import os
import threading

import cv2
import numpy as np
import pytest
from threadpoolctl import threadpool_info

from services.features.sift import SiftExtractor
from services.runtime.spare_workers import SpareWorkers
from services.runtime.threads import (
    ThreadPlan,
    apply_thread_plan,
    opencv_threads,
    plan_threads,
    usable_cores,
)
from tools.synthetic.scene import SyntheticView


class TestPlanThreads:
    @pytest.mark.parametrize(
        ("cores", "workers", "threads", "expected"),
        [
            (1, None, None, (1, 1)),
            (2, None, None, (2, 1)),
            (16, None, None, (4, 4)),
            (2, 1, None, (1, 2)),
            (8, 3, None, (3, 2)),
            (2, None, 2, (1, 2)),
            (16, None, 8, (2, 8)),
            (2, 2, 2, (2, 2)),  # both given: honoured, and flagged
        ],
    )
    def test_sizes(
        self, cores: int, workers: int | None, threads: int | None, expected: tuple[int, int]
    ) -> None:
        plan = plan_threads(cores, workers, threads)
        assert (plan.workers, plan.threads_per_worker) == expected
        assert plan.oversubscribed == (plan.workers * plan.threads_per_worker > cores)

    @pytest.mark.parametrize("cores", range(1, 33))
    def test_defaults_never_oversubscribe(self, cores: int) -> None:
        for threads in (None, 1, 2, 3, cores):
            plan = plan_threads(cores, None, threads)
            assert not plan.oversubscribed or plan.threads_per_worker > cores

    def test_usable_cores_is_the_affinity(self) -> None:
        assert usable_cores() == len(os.sched_getaffinity(0))
        assert plan_threads().cores == usable_cores()

    def test_rejects_zero(self) -> None:
        with pytest.raises(ValueError, match="workers must be at least 1"):
            plan_threads(2, 0, None)


def test_apply_limits_opencv_and_blas() -> None:
    before_cv = cv2.getNumThreads()
    try:
        apply_thread_plan(ThreadPlan(cores=2, workers=2, threads_per_worker=1))
        assert cv2.getNumThreads() == 1
        assert all(pool["num_threads"] == 1 for pool in threadpool_info())
    finally:
        cv2.setNumThreads(before_cv)


def test_opencv_threads_are_set_for_the_block_then_set_back() -> None:
    before = cv2.getNumThreads()
    try:
        cv2.setNumThreads(1)
        with opencv_threads(3):
            assert cv2.getNumThreads() == 3
        assert cv2.getNumThreads() == 1
        with pytest.raises(RuntimeError), opencv_threads(2):
            raise RuntimeError("the block failed")
        assert cv2.getNumThreads() == 1
    finally:
        cv2.setNumThreads(before)


@pytest.mark.parametrize("idle", [True, False])
def test_sift_on_borrowed_workers_finds_the_same_features(
    reference_views: list[SyntheticView], idle: bool
) -> None:
    """SIFT on every worker's threads (when the request can borrow the idle workers) answers as
    on one worker's; OpenCV's threads and the slots are back afterwards, and a busy worker is
    not borrowed."""
    before = cv2.getNumThreads()
    slots = threading.BoundedSemaphore(2)
    spare = SpareWorkers(slots, most=1)
    slots.acquire()  # the request itself
    if not idle:
        slots.acquire()  # another request computing
    image = reference_views[0].image
    try:
        cv2.setNumThreads(1)
        wide = SiftExtractor(wide_threads=2).extract(image, spare)
        assert cv2.getNumThreads() == 1
        narrow = SiftExtractor().extract(image)
        assert slots.acquire(blocking=False) == idle  # the borrowed slot went back
    finally:
        spare.shutdown()
        cv2.setNumThreads(before)
    assert len(wide) == len(narrow) > 500
    np.testing.assert_array_equal(wide.keypoints, narrow.keypoints)
    np.testing.assert_array_equal(wide.descriptors, narrow.descriptors)
