"""The long passes of an estimate poll the deadline: the Sampson errors over all matches (in
chunks, the same errors as in one pass), the generalized refinement (in slices when time is
short) and the 3D verification; the deadline passing inside them is ``time_budget_exceeded``."""

from __future__ import annotations

import numpy as np
import pytest

from services.estimators.base import FailureReason
from services.estimators.correspondences import (
    SAMPSON_CHUNK,
    pose_sampson_errors_px,
    stack_matches,
)
from services.estimators.poselib_bridge import refine_query_pose
from services.estimators.ransac import Deadline, DeadlinePassedError
from services.estimators.registry import get_estimator
from services.estimators.verification import verify_pose
from services.geometry.rigid import Rigid3d
from tests.timing import timed
from tools.synthetic.correspondences import SyntheticCorrespondences, make_correspondences

from .conftest import TEST_OPTIONS


@pytest.fixture(scope="module")
def many() -> SyntheticCorrespondences:
    """30 references of 1000 matches: more than three chunks of a pass."""
    return make_correspondences(seed=3, num_references=30, matches_per_reference=1000)


def _perturbed(pose: Rigid3d) -> Rigid3d:
    return Rigid3d(pose.rotation, pose.translation + np.array([0.05, -0.03, 0.02]))


class TestChunkedSampsonErrors:
    def test_chunks_give_the_errors_of_one_pass(self, many: SyntheticCorrespondences) -> None:
        stacked = stack_matches(many.query_camera, many.references)
        assert stacked.size > 3 * SAMPSON_CHUNK
        rng = np.random.default_rng(0)
        R = np.linalg.qr(rng.normal(size=(4, 3, 3)))[0]
        C = rng.normal(size=(4, 3))
        for subset in (None, rng.choice(stacked.size, 20_000, replace=False)):
            whole = pose_sampson_errors_px(stacked, R, C, subset)
            chunked = pose_sampson_errors_px(stacked, R, C, subset, Deadline(60.0))
            np.testing.assert_array_equal(chunked, whole)

    def test_a_passed_deadline_ends_the_pass(self, many: SyntheticCorrespondences) -> None:
        stacked = stack_matches(many.query_camera, many.references)
        pose = many.query_pose
        with pytest.raises(DeadlinePassedError):
            pose_sampson_errors_px(
                stacked, pose.rotation[None], pose.center[None], None, Deadline(0)
            )


class TestRefinementWithinTime:
    def test_ample_time_is_one_refinement(self, many: SyntheticCorrespondences) -> None:
        masks = many.inlier_masks
        start = _perturbed(many.query_pose)
        plain = refine_query_pose(many.references, masks, many.query_camera, start, 2.0)
        timed = refine_query_pose(
            many.references, masks, many.query_camera, start, 2.0, deadline=Deadline(60.0)
        )
        np.testing.assert_array_equal(timed.matrix, plain.matrix)

    def test_short_time_ends_before_the_reserve(self, many: SyntheticCorrespondences) -> None:
        masks = [np.ones(ref.num_matches, bool) for ref in many.references]
        # one slice may run over (0.1 s at the measured throughput), on a loaded machine more
        limit_s = 0.15 + 0.3
        elapsed, refined = timed(
            lambda: refine_query_pose(
                many.references,
                masks,
                many.query_camera,
                _perturbed(many.query_pose),
                2.0,
                max_iterations=100_000,
                deadline=Deadline(0.15),
                reserve_s=0.05,
            ),
            limit_s,
        )
        assert elapsed < limit_s
        assert np.all(np.isfinite(refined.matrix))

    def test_no_time_left_keeps_the_pose(self, many: SyntheticCorrespondences) -> None:
        start = _perturbed(many.query_pose)
        out = refine_query_pose(
            many.references, many.inlier_masks, many.query_camera, start, 2.0, 100, Deadline(0)
        )
        assert out is start


def test_verification_out_of_time_is_time_budget_exceeded(
    many: SyntheticCorrespondences,
) -> None:
    found = get_estimator("e5p1").estimate(many.query_camera, many.references, TEST_OPTIONS)
    assert found.cam_from_world is not None
    unbounded = verify_pose(found, many.query_camera, many.references, TEST_OPTIONS)
    assert unbounded.failure_reason is None
    timed = verify_pose(found, many.query_camera, many.references, TEST_OPTIONS, Deadline(60.0))
    assert timed == unbounded
    late = verify_pose(found, many.query_camera, many.references, TEST_OPTIONS, Deadline(0))
    assert late.failure_reason is FailureReason.TIME_BUDGET_EXCEEDED
    assert late.cam_from_world is None
