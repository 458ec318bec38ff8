"""Joint pose of several frames with known session poses (``rig_pose``) on synthetic
correspondences with exact ground truth."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from services.estimators.base import FailureReason
from services.estimators.options import EstimatorOptions, RansacOptions
from services.estimators.registry import get_estimator
from services.estimators.rig_pose import MIN_POINT_INLIER_SHARE, RigFrame, estimate_rig_pose
from services.estimators.uncertainty import (
    pose_uncertainty,
    rig_pose_uncertainty,
    within_target_probability,
)
from services.estimators.verification import check_structure, verify_pose
from services.geometry.rigid import Rigid3d, pose_error, rotation_error_deg
from tools.synthetic.correspondences import SyntheticCorrespondences, make_correspondences

OPTIONS = EstimatorOptions(ransac=RansacOptions(min_iterations=100, max_iterations=2000))
MAP_FROM_SESSION = Rigid3d(cv2.Rodrigues(np.array([0.1, 0.6, -0.2]))[0], np.array([0.8, -0.4, 1.2]))


def _rig(scenes: list[SyntheticCorrespondences]) -> list[RigFrame]:
    """Each scene's query as one frame of a session placed by ``MAP_FROM_SESSION``; each
    scene's references are their own images (ids unique over the scenes, as in a map)."""
    return [
        RigFrame(
            s.query_camera,
            s.query_pose.compose(MAP_FROM_SESSION),
            [replace(r, image_id=f"scene{k}-{r.image_id}") for r in s.references],
        )
        for k, s in enumerate(scenes)
    ]


def _alignment_error(session_from_map: Rigid3d | None) -> tuple[float, float]:
    assert session_from_map is not None
    estimate = session_from_map.inverse()
    return (
        float(np.linalg.norm(estimate.translation - MAP_FROM_SESSION.translation)),
        rotation_error_deg(estimate.rotation, MAP_FROM_SESSION.rotation),
    )


def _scenes(first_seed: int, count: int) -> list[SyntheticCorrespondences]:
    """``count`` queries, 4 references each, 150 matches per reference (1 px noise, 30 %
    outliers) on 3000 room points, so that references share query keypoints (tracks)."""
    return [
        make_correspondences(
            seed=first_seed + i, num_references=4, matches_per_reference=150, num_points=3000
        )
        for i in range(count)
    ]


def test_frames_recover_map_from_session() -> None:
    scenes = _scenes(20, 3)
    frames = _rig(scenes)
    out = estimate_rig_pose(frames, OPTIONS)
    assert out.failure_reason is None, out.stats
    dt, dr = _alignment_error(out.session_from_map)
    assert dt < 0.01 and dr < 0.2
    for frame, scene in zip(frames, scenes, strict=True):
        pose = out.cam_from_map(frame)
        assert pose is not None
        ft, fr = pose_error(pose, scene.query_pose)
        assert ft < 0.01 and fr < 0.2
    # the inliers are mostly the true correspondences (30 % outliers in the input)
    for masks, scene in zip(out.inliers, scenes, strict=True):
        truth = np.concatenate(scene.inlier_masks)
        found = np.concatenate(masks)
        assert (found & truth).sum() >= 0.9 * truth.sum()
        assert (found & ~truth).sum() <= 0.1 * (~truth).sum()
    assert all(n > 0 for n in out.point_inliers)
    assert 0.0 < out.confidence < 1.0


def test_joint_is_more_accurate_than_each_frame_alone() -> None:
    scenes = _scenes(20, 3)
    frames = _rig(scenes)
    joint = estimate_rig_pose(frames, OPTIONS)
    single = get_estimator("local_tri_all")
    for frame, scene in zip(frames, scenes, strict=True):
        alone = single.estimate(scene.query_camera, scene.references, OPTIONS).cam_from_world
        pose = joint.cam_from_map(frame)
        assert alone is not None and pose is not None
        assert pose_error(pose, scene.query_pose)[0] < pose_error(alone, scene.query_pose)[0]


def test_frames_too_weak_alone_localize_jointly() -> None:
    # 10 matches per reference, 3 references: a frame triangulates 0-4 points, too few to be
    # localized alone; the five frames together have 10
    scenes = [
        make_correspondences(
            seed=40 + i,
            num_references=3,
            matches_per_reference=10,
            outlier_ratio=0.1,
            num_points=600,
        )
        for i in range(5)
    ]
    single = get_estimator("local_tri_all")
    for scene in scenes:
        alone = verify_pose(
            single.estimate(scene.query_camera, scene.references, OPTIONS),
            scene.query_camera,
            scene.references,
            OPTIONS,
        )
        assert alone.cam_from_world is None
    out = estimate_rig_pose(_rig(scenes), OPTIONS)
    assert out.failure_reason is None, out.stats
    dt, dr = _alignment_error(out.session_from_map)
    assert dt < 0.05 and dr < 0.5


def test_inconsistent_session_poses_are_refused() -> None:
    # session poses that belong to a different trajectory: no rigid transform explains them
    scenes = _scenes(60, 3)
    frames = _rig(scenes)
    rng = np.random.default_rng(0)
    scrambled = [
        RigFrame(
            f.camera,
            Rigid3d(cv2.Rodrigues(rng.normal(size=3))[0], rng.normal(size=3) * 3.0).compose(
                f.cam_from_session
            ),
            f.references,
        )
        for f in frames
    ]
    out = estimate_rig_pose(scrambled, OPTIONS)
    if out.session_from_map is not None:  # one frame may carry a consistent answer alone
        assert (
            out.stats["frames_with_points"] < 3 or _alignment_error(out.session_from_map)[0] > 0.1
        )
    assert out.num_inliers < sum(int(np.concatenate(s.inlier_masks).sum()) for s in scenes)


def test_no_references_and_too_few_matches() -> None:
    scene = make_correspondences(seed=80, num_references=3, matches_per_reference=20)
    empty = RigFrame(scene.query_camera, scene.query_pose, [])
    assert estimate_rig_pose([empty, empty], OPTIONS).failure_reason == FailureReason.NO_REFERENCES
    few = [
        r.__class__(
            **{**r.__dict__, "query_xy": r.query_xy[:1], "reference_xy": r.reference_xy[:1]}
        )
        for r in scene.references
    ]
    out = estimate_rig_pose([RigFrame(scene.query_camera, scene.query_pose, few)] * 2, OPTIONS)
    assert out.failure_reason == FailureReason.TOO_FEW_MATCHES
    assert out.session_from_map is None and out.num_inliers == 0


def test_joint_uncertainty_covers_the_error_and_is_below_one_frames() -> None:
    """The joint answer's uncertainty (the first frame's pose) covers its error within 3σ and
    is narrower than the first frame's own answer's; the confidence stays below the
    probability it leaves for 25 cm and 5°."""
    scenes = _scenes(20, 3)
    frames = _rig(scenes)
    out = estimate_rig_pose(frames, OPTIONS)
    assert out.uncertainty is not None, out.stats
    pose = out.cam_from_map(frames[0], 0)
    assert pose is not None
    dt, dr = pose_error(pose, scenes[0].query_pose)
    assert dt < 3 * out.uncertainty.position_m and dr < 3 * out.uncertainty.rotation_deg
    assert out.stats["structure_position_sigma_m"] == out.uncertainty.position_m
    alone = verify_pose(
        get_estimator("local_tri_all").estimate(
            scenes[0].query_camera, scenes[0].references, OPTIONS
        ),
        scenes[0].query_camera,
        scenes[0].references,
        OPTIONS,
    )
    single = pose_uncertainty(alone, scenes[0].query_camera, scenes[0].references, OPTIONS, False)
    assert single is not None
    assert out.uncertainty.position_m < single.position_m
    assert out.uncertainty.rotation_deg < single.rotation_deg
    assert out.confidence <= within_target_probability(out.uncertainty, OPTIONS.uncertainty)


def _query_keypoints_swapped(scene: SyntheticCorrespondences, share: float, seed: int) -> list:
    """The scene's references with ``share`` of the query keypoints swapped among themselves
    (the same swap in every reference): the references still triangulate every point where
    it is, but those points' query pixels are another point's."""
    pixels = np.unique(np.concatenate([r.query_xy for r in scene.references]), axis=0)
    rng = np.random.default_rng(seed)
    chosen = rng.choice(len(pixels), round(share * len(pixels)), replace=False)
    moved = pixels.copy()
    moved[chosen] = pixels[np.roll(chosen, 1)]
    lookup = {tuple(p): m for p, m in zip(pixels, moved, strict=True)}
    return [
        replace(r, query_xy=np.array([lookup[tuple(p)] for p in r.query_xy]))
        for r in scene.references
    ]


def test_a_joint_pose_that_fits_few_points_is_refused() -> None:
    """With 70 % of every frame's query keypoints swapped, the true pose fits about a third
    of the triangulated points: below ``MIN_POINT_INLIER_SHARE``, ``no_consensus``; with 30 %
    swapped, the same frames are localized."""
    scenes = _scenes(20, 3)
    for share, refused in ((0.7, True), (0.3, False)):
        frames = [
            RigFrame(f.camera, f.cam_from_session, _query_keypoints_swapped(s, share, k))
            for k, (f, s) in enumerate(zip(_rig(scenes), scenes, strict=True))
        ]
        out = estimate_rig_pose(frames, OPTIONS)
        if refused:
            assert out.failure_reason == FailureReason.NO_CONSENSUS, out.stats
            assert out.stats["points_inlier_share"] < MIN_POINT_INLIER_SHARE
        else:
            assert out.failure_reason is None, out.stats
            assert out.stats["points_inlier_share"] >= MIN_POINT_INLIER_SHARE
            assert _alignment_error(out.session_from_map)[0] < 0.05


def test_points_that_frames_share_are_one_point() -> None:
    """The same frame sent twice (same references, same keypoints, same pose): every point of
    the second merges with the first's, so the points are the frame's alone, and with them
    taken as exact the pose's variance halves (each point observed twice)."""
    scene = _scenes(20, 1)[0]
    checked = check_structure(
        scene.query_camera,
        scene.query_pose,
        scene.references,
        scene.inlier_masks,
        OPTIONS.ransac.max_error_px,
    )
    assert checked is not None
    options = OPTIONS.uncertainty
    one = rig_pose_uncertainty([scene.query_pose], [scene.query_camera], [checked], options)
    two = rig_pose_uncertainty(
        [scene.query_pose] * 2, [scene.query_camera] * 2, [checked] * 2, options
    )
    assert one is not None and two is not None
    assert two.num_points == one.num_points == int(checked.check.point_verified.sum())
    ratio = two.given_points_position_m / one.given_points_position_m
    assert abs(ratio - np.sqrt(0.5)) < 0.01, ratio
    assert two.position_m < one.position_m
