"""Configurations where epipolar constraints leave the query's position unobservable
(a street driven forward, references on the line through the query) or badly conditioned (a
narrow reference baseline), and the pure-rotation case that is not degenerate. ``e5p1`` and
``essential_5pt`` must say ``degenerate_geometry`` or be right, never confidently wrong;
``auto`` must localize the street frames."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from services.estimators.auto import AutoEstimator, agreement_stats, choose, plan_estimators
from services.estimators.base import EstimateResult, FailureReason, ReferenceObservation
from services.estimators.options import EstimatorOptions
from services.estimators.position_conditioning import (
    ReferenceLayout,
    reference_layout,
    reference_spread_deg,
)
from services.estimators.registry import get_estimator
from services.estimators.verification import verify_pose
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d, pose_error
from tests.estimators.conftest import TEST_OPTIONS
from tools.synthetic.configurations import narrow_baseline, pure_rotation, street
from tools.synthetic.correspondences import SyntheticCorrespondences

STREET_SEEDS = range(20)


def _answer(name: str, scene: SyntheticCorrespondences) -> EstimateResult:
    """What the service answers: the estimator, then the pipeline's 3D verification."""
    result = get_estimator(name).estimate(scene.query_camera, scene.references, TEST_OPTIONS)
    return verify_pose(result, scene.query_camera, scene.references, TEST_OPTIONS)


def _correct(result: EstimateResult, scene: SyntheticCorrespondences) -> bool:
    """Within (1 % of the scene depth, 0.5°) of the ground truth."""
    assert result.cam_from_world is not None
    position, rotation = pose_error(result.cam_from_world, scene.query_pose)
    return position < 0.01 * scene.scene_depth and rotation < 0.5


@pytest.fixture(scope="module")
def streets() -> list[SyntheticCorrespondences]:
    return [street(seed) for seed in STREET_SEEDS]


def test_auto_localizes_forward_motion(streets: list[SyntheticCorrespondences]) -> None:
    correct = 0
    for scene in streets:
        result = _answer("auto", scene)
        assert result.estimator_used in {"local_tri_all", "motion_averaging"}
        assert result.estimator_reason and "forward motion" in result.estimator_reason
        correct += result.cam_from_world is not None and _correct(result, scene)
    assert correct >= 0.95 * len(streets), f"{correct} of {len(streets)}"


@pytest.mark.parametrize("name", ["e5p1", "essential_5pt"])
def test_baseline_estimators_are_never_confidently_wrong_on_a_street(
    name: str, streets: list[SyntheticCorrespondences]
) -> None:
    degenerate = 0
    for scene in streets:
        result = _answer(name, scene)
        if result.cam_from_world is None:
            degenerate += result.failure_reason is FailureReason.DEGENERATE_GEOMETRY
        else:
            assert _correct(result, scene) or result.confidence <= 0.5, result.stats
    assert degenerate >= 0.9 * len(streets)


@pytest.mark.parametrize("seed", range(3))
def test_a_street_far_from_the_line_is_not_degenerate(seed: int) -> None:
    """References along the street but spread sideways by metres: the position is observable,
    and e5p1 localizes."""
    scene = street(seed, lateral_jitter_m=3.0)
    result = _answer("e5p1", scene)
    assert result.failure_reason is None, result.stats
    assert _correct(result, scene)


@pytest.mark.parametrize("name", ["e5p1", "essential_5pt", "local_tri_all", "auto"])
@pytest.mark.parametrize("seed", range(3))
def test_pure_rotation_query(name: str, seed: int) -> None:
    """The query at a reference's centre: that pair has no baseline, the others fix the
    position."""
    scene = pure_rotation(seed)
    result = _answer(name, scene)
    assert result.cam_from_world is not None, (result.failure_reason, result.stats)
    assert _correct(result, scene)


@pytest.mark.parametrize("name", ["e5p1", "essential_5pt"])
@pytest.mark.parametrize("seed", range(3))
def test_narrow_baseline(name: str, seed: int) -> None:
    """References within ±2 cm of a point, the query 1 m away: they spread about 1° seen from
    the query."""
    scene = narrow_baseline(seed)
    result = _answer(name, scene)
    if result.cam_from_world is None:
        assert result.failure_reason in {
            FailureReason.DEGENERATE_GEOMETRY,
            FailureReason.NO_CONSENSUS,
        }
    else:
        assert _correct(result, scene) or result.confidence <= 0.5


def test_reference_spread_exact_values() -> None:
    origin, ones = np.zeros(3), np.ones(4)
    on_a_line = np.array([[0, 0, 1.0], [0, 0, 3.0], [0, 0, -2.0], [0, 0, 7.0]])
    assert reference_spread_deg(origin, on_a_line, ones) == pytest.approx(0.0, abs=1e-6)
    right_angle = np.array([[2.0, 0, 0], [0, 5.0, 0]])
    assert reference_spread_deg(origin, right_angle, ones[:2]) == pytest.approx(45.0)
    # one reference 10° off the line of three, equal weights: 1 − the largest eigenvalue of
    # ¾·zzᵀ + ¼·vvᵀ is (1 − √(1 − ¾ sin²10°)) / 2
    angle = np.radians(10.0)
    tilted = np.array([[0, 0, 1.0], [0, 0, 2.0], [0, 0, 3.0], [np.sin(angle), 0, np.cos(angle)]])
    smallest = (1.0 - np.sqrt(1.0 - 0.75 * np.sin(angle) ** 2)) / 2.0
    expected = np.degrees(np.arcsin(np.sqrt(smallest)))
    assert reference_spread_deg(origin, tilted, ones) == pytest.approx(expected, rel=1e-2)
    # a single reference gives no spread; a zero weight does not count
    assert reference_spread_deg(origin, on_a_line[:1], ones[:1]) == 0.0
    assert reference_spread_deg(origin, np.eye(3)[:2], np.array([1.0, 0.0])) == 0.0


def test_reference_layout() -> None:
    along_z = np.array([[0, 0, z] for z in (0.0, 1.5, 3.0, 4.5)])
    looking_z = np.tile([0.0, 0.0, 1.0], (4, 1))
    forward = reference_layout(along_z, looking_z, np.ones(4))
    assert forward.forward_motion
    assert forward.collinearity == pytest.approx(0.0, abs=1e-9)
    assert forward.line_view_angle_deg == pytest.approx(0.0, abs=1e-6)
    sideways = reference_layout(along_z[:, [2, 1, 0]], looking_z, np.ones(4))
    assert not sideways.forward_motion
    assert sideways.line_view_angle_deg == pytest.approx(90.0)
    square = np.array([[0, 0, 0], [1.0, 0, 0], [0, 0, 1.0], [1.0, 0, 1.0]])
    assert reference_layout(square, looking_z, np.ones(4)).collinearity == pytest.approx(1.0)


def test_plans() -> None:
    forward = ReferenceLayout(extent_m=5.0, collinearity=0.01, line_view_angle_deg=3.0)
    spread = ReferenceLayout(extent_m=1.0, collinearity=0.6, line_view_angle_deg=60.0)
    assert plan_estimators(forward, depth=False).first == ("local_tri_all",)
    assert "e5p1" not in plan_estimators(forward, depth=True).estimators
    assert plan_estimators(spread, depth=False).first == ("e5p1", "local_tri_all")
    assert plan_estimators(spread, depth=True).fallbacks[-1] == "e3p1"
    for plan in (plan_estimators(forward, True), plan_estimators(spread, True)):
        for name in plan.estimators:
            get_estimator(name)  # every planned name is registered


def _with_inliers(count: int, stats: dict[str, float] | None = None) -> EstimateResult:
    return EstimateResult(Rigid3d.identity(), [np.arange(4000) < count], stats=stats or {})


def test_choose_prefers_local_triangulation_unless_it_lost_inliers() -> None:
    near = {"e5p1": _with_inliers(3726), "local_tri_all": _with_inliers(3718)}
    assert choose(near)[0] == "local_tri_all"
    lost = {"e5p1": _with_inliers(384), "local_tri_all": _with_inliers(344)}
    name, why = choose(lost)
    assert name == "e5p1" and "384" in why and "344" in why
    assert choose({"e5p1": _with_inliers(10)})[0] == "e5p1"
    assert choose({"motion_averaging": _with_inliers(10), "e3p1": _with_inliers(20)})[0] == "e3p1"


@pytest.mark.parametrize(("points_inliers", "expected"), [(240, "local_tri_all"), (236, "e5p1")])
def test_choose_drops_local_triangulation_whose_points_do_not_fit(
    points_inliers: float, expected: str
) -> None:
    points = {"points_triangulated": 400.0, "points_inliers": points_inliers}
    verified = {"e5p1": _with_inliers(900), "local_tri_all": _with_inliers(905, points)}
    name, why = choose(verified)
    assert name == expected
    if expected == "e5p1":
        assert "59%" in why


class _AlwaysDegenerate:
    name = "e5p1"
    needs_depth = False

    def estimate(
        self,
        query_camera: Camera,
        references: list[ReferenceObservation],
        options: EstimatorOptions,
    ) -> EstimateResult:
        return EstimateResult.failure(FailureReason.DEGENERATE_GEOMETRY, references)


def test_auto_falls_back_and_says_why(scene: SyntheticCorrespondences) -> None:
    """E5+1 fails: local triangulation answers, the reason says so, and the fallbacks are not
    run."""
    refs = [replace(ref, query_depth=None, reference_depth=None) for ref in scene.references]
    candidates = {name: get_estimator(name) for name in ("local_tri_all", "motion_averaging")}
    auto = AutoEstimator({**candidates, "e5p1": _AlwaysDegenerate()})
    result = auto.estimate(scene.query_camera, refs, TEST_OPTIONS)
    assert result.estimator_used == "local_tri_all"
    assert result.estimator_reason and "failed: e5p1 degenerate_geometry" in result.estimator_reason
    assert result.stats["auto_attempts"] == 2.0
    assert result.cam_from_world is not None
    position, rotation = pose_error(result.cam_from_world, scene.query_pose)
    assert position < 0.01 * scene.scene_depth and rotation < 0.5


def test_auto_reports_how_far_its_verified_poses_agree(scene: SyntheticCorrespondences) -> None:
    """Both first-stage estimators verify on a clean scene: the answer carries their
    disagreement, small against the scene; with one pose verified there is none."""
    refs = [replace(ref, query_depth=None, reference_depth=None) for ref in scene.references]
    candidates = {n: get_estimator(n) for n in ("e5p1", "local_tri_all", "motion_averaging")}
    result = AutoEstimator(candidates).estimate(scene.query_camera, refs, TEST_OPTIONS)
    assert result.stats["auto_verified_poses"] == 2.0
    assert 0.0 <= result.stats["auto_other_position_m"] < 0.01 * scene.scene_depth
    assert 0.0 <= result.stats["auto_other_rotation_deg"] < 0.5
    alone = AutoEstimator({**candidates, "e5p1": _AlwaysDegenerate()})
    stats = alone.estimate(scene.query_camera, refs, TEST_OPTIONS).stats
    assert stats["auto_verified_poses"] == 1.0 and "auto_other_position_m" not in stats


def test_agreement_stats_are_the_largest_over_the_other_poses() -> None:
    turned = Rigid3d(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), np.zeros(3))
    verified = {
        "local_tri_all": _with_inliers(100),
        "e5p1": replace(
            _with_inliers(90), cam_from_world=Rigid3d(np.eye(3), np.array([3.0, 4.0, 0.0]))
        ),
        "e3p1": replace(_with_inliers(80), cam_from_world=turned),
    }
    stats = agreement_stats(verified, "local_tri_all")
    assert stats["auto_verified_poses"] == 3.0
    assert stats["auto_other_position_m"] == pytest.approx(5.0)
    assert stats["auto_other_rotation_deg"] == pytest.approx(90.0)


def test_auto_reports_the_first_failure_when_all_fail(scene: SyntheticCorrespondences) -> None:
    refs = [replace(ref, query_depth=None, reference_depth=None) for ref in scene.references]
    failing = _AlwaysDegenerate()
    auto = AutoEstimator({"e5p1": failing, "local_tri_all": failing, "motion_averaging": failing})
    result = auto.estimate(scene.query_camera, refs, TEST_OPTIONS)
    assert result.failure_reason is FailureReason.DEGENERATE_GEOMETRY
    assert result.estimator_used == "e5p1"
    assert result.estimator_reason and "no estimator localized" in result.estimator_reason


class _UnfitTriangulation:
    """Local triangulation's pose with a quarter of its triangulated points fitting it."""

    name = "local_tri_all"
    needs_depth = False

    def estimate(
        self,
        query_camera: Camera,
        references: list[ReferenceObservation],
        options: EstimatorOptions,
    ) -> EstimateResult:
        result = get_estimator("local_tri_all").estimate(query_camera, references, options)
        unfit = {"points_triangulated": 400.0, "points_inliers": 100.0}
        return replace(result, stats=result.stats | unfit)


def test_local_triangulation_whose_points_do_not_fit_is_no_answer_alone(
    scene: SyntheticCorrespondences,
) -> None:
    """E5+1 fails and local triangulation's points do not fit its pose: the query is not
    localized, the reason says why, and the fallback is not run in its place."""
    refs = [replace(ref, query_depth=None, reference_depth=None) for ref in scene.references]
    candidates = {
        "e5p1": _AlwaysDegenerate(),
        "local_tri_all": _UnfitTriangulation(),
        "motion_averaging": get_estimator("motion_averaging"),
    }
    result = AutoEstimator(candidates).estimate(scene.query_camera, refs, TEST_OPTIONS)
    assert result.cam_from_world is None
    assert result.failure_reason is FailureReason.DEGENERATE_GEOMETRY
    assert result.stats["auto_attempts"] == 2.0
    assert result.estimator_reason and "25% of its triangulated points" in result.estimator_reason
    with_e5p1 = AutoEstimator({**candidates, "e5p1": get_estimator("e5p1")})
    result = with_e5p1.estimate(scene.query_camera, refs, TEST_OPTIONS)
    assert result.estimator_used == "e5p1" and result.cam_from_world is not None


def test_on_a_street_unfit_local_triangulation_alone_is_no_consensus(
    streets: list[SyntheticCorrespondences],
) -> None:
    """Forward motion runs local triangulation first: unfit and alone, it is no answer."""
    scene = streets[0]
    failing = _AlwaysDegenerate()
    candidates = {
        "e5p1": failing,
        "local_tri_all": _UnfitTriangulation(),
        "motion_averaging": failing,
    }
    result = AutoEstimator(candidates).estimate(scene.query_camera, scene.references, TEST_OPTIONS)
    assert result.cam_from_world is None
    assert result.failure_reason is FailureReason.NO_CONSENSUS
    assert result.estimator_used == "local_tri_all"
