"""One contract over every registered estimator: the same synthetic correspondences from
exact ground truth, accuracy bounds, result shape, and localized failures."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from services.estimators.base import (
    EstimateResult,
    FailureReason,
    ReferenceObservation,
)
from services.estimators.options import E3p1Options, PoseApproxMode, PoseApproxOptions
from services.estimators.registry import DEPTH_ESTIMATORS, estimator_names, get_estimator
from services.geometry.camera import Camera
from services.geometry.rigid import pose_error
from tests.estimators.conftest import TEST_OPTIONS
from tools.synthetic.correspondences import SyntheticCorrespondences

ALL = estimator_names()
GEOMETRIC = [name for name in ALL if name != "pose_approx"]


def test_registry_has_the_whole_family() -> None:
    assert set(ALL) == {
        "auto",
        "pose_approx",
        "essential_5pt",
        "essential_3pt_depth",
        "motion_averaging",
        "e5p1",
        "e3p1",
        "local_tri_all",
        "local_tri_pairs",
    }


def _check_shape(result: EstimateResult, references: list[ReferenceObservation]) -> None:
    assert len(result.inliers) == len(references)
    for mask, ref in zip(result.inliers, references, strict=True):
        assert mask.dtype == bool and mask.shape == (ref.num_matches,)
    assert 0.0 <= result.confidence <= 1.0
    assert (result.cam_from_world is None) == (result.failure_reason is not None)


@pytest.mark.parametrize("name", ALL)
def test_recovers_ground_truth(name: str, scene: SyntheticCorrespondences) -> None:
    result = get_estimator(name).estimate(scene.query_camera, scene.references, TEST_OPTIONS)
    _check_shape(result, scene.references)
    assert result.failure_reason is None, result.stats
    assert result.cam_from_world is not None
    position, rotation = pose_error(result.cam_from_world, scene.query_pose)
    if name == "pose_approx":
        # a baseline: somewhere among the references, never exact
        assert position < 3.0 and rotation < 15.0
        assert result.num_inliers == 0 and result.confidence <= 0.1
        return
    assert rotation < 0.5, (position, rotation)
    assert position < 0.01 * scene.scene_depth, (position, rotation)
    assert "iterations" in result.stats and "inlier_ratio" in result.stats
    flagged = np.concatenate(result.inliers)
    truth = np.concatenate(scene.inlier_masks)
    assert flagged[truth].mean() > 0.9  # recall of the true correspondences
    assert truth[flagged].mean() > 0.9  # precision (wrong matches can pass a 12 px test)
    assert result.confidence > 0.5


@pytest.mark.parametrize("name", ALL)
def test_no_references(name: str, scene: SyntheticCorrespondences) -> None:
    result = get_estimator(name).estimate(scene.query_camera, [], TEST_OPTIONS)
    assert result.cam_from_world is None
    assert result.failure_reason in {FailureReason.NO_REFERENCES, FailureReason.TOO_FEW_MATCHES}


@pytest.mark.parametrize("name", GEOMETRIC)
def test_too_few_matches(name: str, scene: SyntheticCorrespondences) -> None:
    refs = [
        dataclasses.replace(
            ref,
            query_xy=ref.query_xy[:2],
            reference_xy=ref.reference_xy[:2],
            query_depth=None if ref.query_depth is None else ref.query_depth[:2],
            reference_depth=None if ref.reference_depth is None else ref.reference_depth[:2],
        )
        for ref in scene.references[:3]
    ]
    result = get_estimator(name).estimate(scene.query_camera, refs, TEST_OPTIONS)
    _check_shape(result, refs)
    assert result.failure_reason is FailureReason.TOO_FEW_MATCHES


@pytest.mark.parametrize("name", GEOMETRIC)
def test_single_reference(name: str, scene: SyntheticCorrespondences) -> None:
    refs = scene.references[:1]
    result = get_estimator(name).estimate(scene.query_camera, refs, TEST_OPTIONS)
    _check_shape(result, refs)
    assert result.failure_reason is FailureReason.TOO_FEW_MATCHES


@pytest.mark.parametrize("name", GEOMETRIC)
def test_empty_pairs_besides_one(name: str, scene: SyntheticCorrespondences) -> None:
    """The PoseLib hang case: one non-empty pair among empty ones (arrays of shape (0, 2))."""
    empty = dataclasses.replace(
        scene.references[1],
        query_xy=np.zeros((0, 2)),
        reference_xy=np.zeros((0, 2)),
        query_depth=np.zeros(0),
        reference_depth=np.zeros(0),
    )
    refs = [scene.references[0], empty, empty]
    result = get_estimator(name).estimate(scene.query_camera, refs, TEST_OPTIONS)
    _check_shape(result, refs)
    assert result.failure_reason is FailureReason.TOO_FEW_MATCHES


@pytest.mark.parametrize("name", GEOMETRIC)
def test_coincident_reference_centres(
    name: str, coincident_scene: SyntheticCorrespondences
) -> None:
    scene = coincident_scene
    result = get_estimator(name).estimate(scene.query_camera, scene.references, TEST_OPTIONS)
    _check_shape(result, scene.references)
    assert result.failure_reason is FailureReason.DEGENERATE_GEOMETRY


@pytest.mark.parametrize("name", GEOMETRIC)
def test_exhausted_time_budget(name: str, scene: SyntheticCorrespondences) -> None:
    options = dataclasses.replace(TEST_OPTIONS, time_budget_s=0.0)
    result = get_estimator(name).estimate(scene.query_camera, scene.references, options)
    _check_shape(result, scene.references)
    assert result.failure_reason is FailureReason.TIME_BUDGET_EXCEEDED


@pytest.mark.parametrize("name", GEOMETRIC)
def test_only_outliers(name: str, scene: SyntheticCorrespondences) -> None:
    """Wrong matches only. 30 per reference: with the default loose 12 px epipolar threshold a
    few percent of random matches fit any pose, so with hundreds of random matches the
    min_inliers = 30 test alone cannot reject them (a known limit of inlier-count tests)."""
    rng = np.random.default_rng(3)
    refs = [
        dataclasses.replace(
            ref,
            query_xy=ref.query_xy[:30],
            reference_xy=rng.uniform([0, 0], [640, 480], (30, 2)),
            query_depth=None if ref.query_depth is None else ref.query_depth[:30],
            reference_depth=None if ref.reference_depth is None else ref.reference_depth[:30],
        )
        for ref in scene.references[:4]
    ]
    result = get_estimator(name).estimate(scene.query_camera, refs, TEST_OPTIONS)
    _check_shape(result, refs)
    assert result.cam_from_world is None
    assert result.failure_reason is not None


@pytest.mark.parametrize("name", sorted(DEPTH_ESTIMATORS))
def test_depth_estimators_without_depth(name: str, scene: SyntheticCorrespondences) -> None:
    refs = [
        dataclasses.replace(ref, query_depth=None, reference_depth=None) for ref in scene.references
    ]
    result = get_estimator(name).estimate(scene.query_camera, refs, TEST_OPTIONS)
    _check_shape(result, refs)
    assert result.failure_reason is FailureReason.MISSING_DEPTH


@pytest.mark.parametrize("name", sorted(DEPTH_ESTIMATORS))
@pytest.mark.parametrize("side", ["query_depth", "reference_depth"])
def test_depth_estimators_with_one_side_without_depth(
    name: str, side: str, scene: SyntheticCorrespondences
) -> None:
    """Issue 14: the reason says that depth is missing, not that matches are too few."""
    refs = [dataclasses.replace(ref, **{side: None}) for ref in scene.references]
    result = get_estimator(name).estimate(scene.query_camera, refs, TEST_OPTIONS)
    _check_shape(result, refs)
    assert result.failure_reason is FailureReason.MISSING_DEPTH


def test_e3p1_up_to_scale_depth(scene: SyntheticCorrespondences) -> None:
    """Depths known only up to one scale per image: the 3+1 sample fixes the scale."""
    scaled = [
        dataclasses.replace(
            ref,
            query_depth=None if ref.query_depth is None else ref.query_depth * 0.37,
            reference_depth=None if ref.reference_depth is None else ref.reference_depth * 2.1,
        )
        for ref in scene.references
    ]
    options = dataclasses.replace(TEST_OPTIONS, e3p1=E3p1Options(metric_depth=False))
    result = get_estimator("e3p1").estimate(scene.query_camera, scaled, options)
    assert result.cam_from_world is not None, result.failure_reason
    position, rotation = pose_error(result.cam_from_world, scene.query_pose)
    assert rotation < 0.5 and position < 0.01 * scene.scene_depth


def test_pose_approx_top1(scene: SyntheticCorrespondences) -> None:
    options = dataclasses.replace(
        TEST_OPTIONS, pose_approx=PoseApproxOptions(mode=PoseApproxMode.TOP1)
    )
    result = get_estimator("pose_approx").estimate(scene.query_camera, scene.references, options)
    best = max(scene.references, key=lambda ref: ref.retrieval_score)
    assert result.cam_from_world is not None
    np.testing.assert_allclose(result.cam_from_world.center, best.cam_from_world.center)


@pytest.mark.parametrize("name", ["essential_5pt", "e3p1", "local_tri_all", "motion_averaging"])
def test_distorted_camera_model_path(name: str, scene: SyntheticCorrespondences) -> None:
    """OPENCV cameras (zero distortion) go through pycolmap's (un)projection: same answer."""
    fx, fy, cx, cy = scene.query_camera.params
    opencv = Camera("OPENCV", 640, 480, (fx, fy, cx, cy, 0.0, 0.0, 0.0, 0.0))
    refs = [dataclasses.replace(ref, camera=opencv) for ref in scene.references]
    result = get_estimator(name).estimate(opencv, refs, TEST_OPTIONS)
    assert result.cam_from_world is not None, result.failure_reason
    position, rotation = pose_error(result.cam_from_world, scene.query_pose)
    assert rotation < 0.5 and position < 0.01 * scene.scene_depth
