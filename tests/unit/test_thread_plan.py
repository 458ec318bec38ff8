"""The thread policy: workers × threads per operation within the cores (issue #13)."""

from __future__ import annotations

import os

import cv2
import pytest
from threadpoolctl import threadpool_info

from services.runtime.threads import ThreadPlan, apply_thread_plan, plan_threads, usable_cores


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
