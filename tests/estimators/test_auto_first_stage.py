"""``auto`` runs its first-stage estimators at once on an idle worker, with the same answer as
one after the other."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from dataclasses import replace

import numpy as np
import pytest

from services.estimators.auto import AutoEstimator
from services.estimators.base import EstimateResult, PoseEstimator, ReferenceObservation
from services.estimators.options import EstimatorOptions
from services.estimators.registry import get_estimator
from services.geometry.camera import Camera
from services.runtime.spare_workers import SpareWorkers
from tests.estimators.conftest import TEST_OPTIONS
from tools.synthetic.correspondences import SyntheticCorrespondences


class _Together:
    """An estimator that waits, inside ``estimate``, until ``barrier`` has all its parties:
    it ends only if they run at the same time. Records the thread it ran on."""

    def __init__(self, inner: PoseEstimator, barrier: threading.Barrier) -> None:
        self.inner = inner
        self.name = inner.name
        self.needs_depth = inner.needs_depth
        self.barrier = barrier
        self.threads: list[int] = []

    def estimate(
        self,
        query_camera: Camera,
        references: list[ReferenceObservation],
        options: EstimatorOptions,
    ) -> EstimateResult:
        self.threads.append(threading.get_ident())
        self.barrier.wait()
        return self.inner.estimate(query_camera, references, options)


@pytest.fixture
def spare() -> Iterator[SpareWorkers]:
    workers = SpareWorkers(threading.BoundedSemaphore(2), most=1)
    yield workers
    workers.shutdown()


def test_first_stage_at_once_on_an_idle_worker_answers_alike(
    scene: SyntheticCorrespondences, spare: SpareWorkers
) -> None:
    auto = get_estimator("auto")
    assert isinstance(auto, AutoEstimator)
    alone = auto.estimate(scene.query_camera, scene.references, TEST_OPTIONS)
    assert "references spread around the query" in (alone.estimator_reason or "")
    assert alone.stats["auto_attempts"] == 2  # e5p1 and local_tri_all, both verified

    barrier = threading.Barrier(2, timeout=10)
    together = {n: _Together(e, barrier) for n, e in auto.candidates.items()}
    spread = replace(TEST_OPTIONS, spread=spare.split)
    at_once = AutoEstimator(together).estimate(scene.query_camera, scene.references, spread)

    # both ran, each on its own thread (the barrier broke otherwise)
    ran = [n for n, e in together.items() if e.threads]
    assert sorted(ran) == ["e5p1", "local_tri_all"]
    assert together["e5p1"].threads != together["local_tri_all"].threads
    assert at_once.estimator_used == alone.estimator_used
    assert at_once.num_inliers == alone.num_inliers
    assert at_once.cam_from_world is not None and alone.cam_from_world is not None
    assert np.array_equal(at_once.cam_from_world.matrix, alone.cam_from_world.matrix)
    assert at_once.stats == alone.stats


def test_no_idle_worker_runs_the_first_stage_on_the_caller(
    scene: SyntheticCorrespondences,
) -> None:
    busy = SpareWorkers(threading.BoundedSemaphore(1), most=1)
    auto = get_estimator("auto")
    assert isinstance(auto, AutoEstimator)
    barrier = threading.Barrier(1)
    together = {n: _Together(e, barrier) for n, e in auto.candidates.items()}
    try:
        with busy.borrow():  # the one slot taken: nothing to lend
            spread = replace(TEST_OPTIONS, spread=busy.split)
            result = AutoEstimator(together).estimate(scene.query_camera, scene.references, spread)
    finally:
        busy.shutdown()
    assert result.cam_from_world is not None
    caller = threading.get_ident()
    assert together["e5p1"].threads == [caller] and together["local_tri_all"].threads == [caller]
