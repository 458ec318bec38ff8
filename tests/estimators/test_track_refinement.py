"""The last refinement of local triangulation's pose (``refine_keeping_support``): it sharpens
a RANSAC pose on the points that fit it best, and never returns a pose that fewer points fit
than the one it started from. Synthetic 2D–3D matches with exact ground truth: 0.7 px noise and
30 % of the keypoints moved 3–11 px, wrong yet within the 12 px inlier threshold."""

from __future__ import annotations

import cv2
import numpy as np

from services.estimators.options import EstimatorOptions
from services.estimators.poselib_bridge import estimate_absolute_pose, ransac_options
from services.estimators.ransac import Deadline
from services.estimators.tracks import refine_keeping_support, reprojection_errors
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d
from services.types import FloatArray

CAMERA = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))
OPTIONS = EstimatorOptions()
LIMIT_PX = OPTIONS.ransac.max_error_px


def matches(seed: int, count: int) -> tuple[Rigid3d, FloatArray, FloatArray]:
    """The query's true pose, ``count`` world points 2–20 m in front of it, and their noisy
    keypoints (the first 30 % moved 3–11 px)."""
    rng = np.random.default_rng(seed)
    rotation = np.asarray(cv2.Rodrigues(rng.normal(0.0, 0.1, 3))[0], dtype=np.float64)
    pose = Rigid3d(rotation, rng.normal(0.0, 0.5, 3))
    pixels = rng.uniform([0.0, 0.0], [640.0, 480.0], (count, 2))
    depth = rng.uniform(2.0, 20.0, count)
    rays = np.c_[(pixels - [320.0, 240.0]) / 500.0, np.ones(count)] * depth[:, None]
    world = pose.inverse().apply(rays)
    keypoints = pixels + rng.normal(0.0, 0.7, (count, 2))
    moved = int(0.3 * count)
    angle = rng.uniform(0.0, 2.0 * np.pi, moved)
    keypoints[:moved] += np.c_[np.cos(angle), np.sin(angle)] * rng.uniform(3.0, 11.0, (moved, 1))
    return pose, world, keypoints


def support(pose: Rigid3d, world: FloatArray, keypoints: FloatArray) -> int:
    return int(np.count_nonzero(reprojection_errors(pose, world, keypoints, CAMERA) < LIMIT_PX))


def test_refinement_sharpens_the_ransac_pose() -> None:
    before, after = [], []
    for seed in range(20):
        truth, world, keypoints = matches(seed, 40)
        deadline = Deadline(None)
        ransac = ransac_options(
            OPTIONS.ransac, deadline, 1, reprojection_px=LIMIT_PX, num_matches=40
        )
        found = estimate_absolute_pose(keypoints, world, CAMERA, ransac, LIMIT_PX / 4.0)
        assert found is not None
        refined, _ = refine_keeping_support(found[0], world, keypoints, CAMERA, OPTIONS, deadline)
        before.append(np.linalg.norm(found[0].center - truth.center))
        after.append(np.linalg.norm(refined.center - truth.center))
    # PoseLib's loss at a quarter of the 12 px threshold still weighs the moved keypoints
    assert np.mean(after) < 0.8 * np.mean(before)
    assert sum(a < b for a, b in zip(after, before, strict=True)) >= 12


def test_refinement_never_loses_support() -> None:
    kept, refined_count = 0, 0
    for seed in range(30):
        truth, world, keypoints = matches(seed, 20)
        pose, used = refine_keeping_support(
            truth, world, keypoints, CAMERA, OPTIONS, Deadline(None)
        )
        assert support(pose, world, keypoints) >= support(truth, world, keypoints)
        if used == 0:
            kept += 1
            assert pose is truth
        else:
            refined_count += 1
            assert 6 <= used <= 20
    # both outcomes occur on these scenes: the check is exercised, not vacuous
    assert kept >= 1
    assert refined_count >= 20


def test_refinement_stops_at_the_deadline() -> None:
    truth, world, keypoints = matches(0, 40)
    pose, used = refine_keeping_support(truth, world, keypoints, CAMERA, OPTIONS, Deadline(0.0))
    assert pose is truth
    assert used == 0
