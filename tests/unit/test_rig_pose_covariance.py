"""The covariance of a rig's pose (frames whose relative poses are known): its adjoint against
finite differences, one view against ``pose_covariance``, and its predicted spread against the
actual spread of least-squares rig poses (pycolmap's generalized refinement) over many noisy
trials."""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap
import pytest

from services.geometry.pose_covariance import (
    ReferenceViews,
    RigObservations,
    pose_covariance,
    rig_adjoint,
    rig_pose_covariance,
)
from services.geometry.rigid import Rigid3d, pose_error
from tools.synthetic.correspondences import sample_room_points

FOCAL = 500.0


def _pose(rotation: tuple[float, float, float], center: tuple[float, float, float]) -> Rigid3d:
    R = cv2.Rodrigues(np.array(rotation))[0]
    return Rigid3d(R, -R @ np.array(center))


def _perturbed(pose: Rigid3d, delta: np.ndarray) -> Rigid3d:
    """``pose`` turned by ``exp([δθ]×)`` and its centre moved by ``δC``."""
    R = cv2.Rodrigues(delta[:3])[0] @ pose.rotation
    return Rigid3d(R, -R @ (pose.center + delta[3:6]))


def _project(pose: Rigid3d, points: np.ndarray) -> np.ndarray:
    X = pose.apply(points)
    return X[:, :2] / X[:, 2:] * FOCAL


def _visible_points(pose: Rigid3d, count: int, seed: int) -> np.ndarray:
    points = sample_room_points(np.random.default_rng(seed), 20 * count)
    X = pose.apply(points)
    xy = X[:, :2] / X[:, 2:] * FOCAL
    keep = (X[:, 2] > 0.5) & (np.abs(xy[:, 0]) < 320) & (np.abs(xy[:, 1]) < 240)
    return points[keep][:count]


def _two_frames() -> tuple[Rigid3d, Rigid3d]:
    """Two frames of a handheld session: 40 cm apart, turned by about 15°."""
    return _pose((0.05, -0.1, 0.02), (0.4, 0.2, -1.0)), _pose((0.0, 0.15, -0.03), (0.8, 0.1, -0.9))


def test_adjoint_matches_finite_differences() -> None:
    """Turning and moving the first frame moves the second, fixed to it, as the adjoint says."""
    first, other = _two_frames()
    other_from_first = other.compose(first.inverse())
    adjoint = rig_adjoint(first, other)
    step = 1e-4  # OpenCV's Rodrigues reads turns below about 1e-5 rad as none
    for k in range(6):
        delta = np.zeros(6)
        delta[k] = step
        moved = [other_from_first.compose(_perturbed(first, sign * delta)) for sign in (1, -1)]
        turn = cv2.Rodrigues(moved[0].rotation @ moved[1].rotation.T)[0].ravel() / (2 * step)
        shift = (moved[0].center - moved[1].center) / (2 * step)
        np.testing.assert_allclose(np.concatenate([turn, shift]), adjoint[:, k], atol=1e-6)


def test_one_view_of_exact_points_is_the_single_camera_covariance() -> None:
    pose = _two_frames()[0]
    points = _visible_points(pose, 60, 0)
    xy = _project(pose, points) + np.random.default_rng(0).normal(0, 1.0, (60, 2))
    single = pose_covariance(pose, points, xy, FOCAL)
    rig = rig_pose_covariance(
        RigObservations([pose], np.array([FOCAL]), np.zeros(60, int), np.arange(60), xy, points)
    )
    assert single is not None and rig is not None
    np.testing.assert_allclose(rig.covariance, single.covariance, rtol=1e-9)
    assert rig.sigma_px == pytest.approx(single.sigma_px)


def test_predicted_spread_matches_the_actual_spread_of_rig_poses() -> None:
    """Over 200 trials of 1.5 px noise in both frames, the mean squared error of the first
    frame's pose refined jointly (pycolmap's generalized refinement, the second frame fixed to
    it) matches the predicted ``trace Σ`` within 25 %; the prediction is narrower than the
    first frame's alone."""
    first, second = _two_frames()
    points = [_visible_points(first, 50, 1), _visible_points(second, 50, 2)]
    exact = [_project(pose, p) for pose, p in zip((first, second), points, strict=True)]
    second_from_first = second.compose(first.inverse())
    to_colmap = [
        pycolmap.Rigid3d(pycolmap.Rotation3d(p.rotation), p.translation)
        for p in (
            Rigid3d(np.eye(3), np.zeros(3)),
            second_from_first,
        )
    ]
    camera = pycolmap.Camera(model="SIMPLE_PINHOLE", width=640, height=480, params=[FOCAL, 0, 0])
    options = pycolmap.AbsolutePoseRefinementOptions()
    options.loss_function_scale = 1e3  # Cauchy at 1000 px: plain least squares at 1.5 px noise
    rng = np.random.default_rng(3)
    squared, predicted, alone = [], [], []
    for _ in range(200):
        xy = [e + rng.normal(0.0, 1.5, e.shape) for e in exact]
        out = pycolmap.refine_generalized_absolute_pose(
            pycolmap.Rigid3d(pycolmap.Rotation3d(first.rotation), first.translation),
            np.concatenate(xy),
            np.concatenate(points),
            np.ones(100, bool),
            [0] * 50 + [1] * 50,
            to_colmap,
            [camera, camera],
            options,
        )
        assert out is not None
        rig = out["rig_from_world"]
        estimate = Rigid3d(rig.rotation.matrix(), rig.translation)
        observed = RigObservations(
            [estimate, second_from_first.compose(estimate)],
            np.array([FOCAL, FOCAL]),
            np.repeat([0, 1], 50),
            np.arange(100),
            np.concatenate(xy),
            np.concatenate(points),
        )
        covariance = rig_pose_covariance(observed)
        single = pose_covariance(estimate, points[0], xy[0], FOCAL)
        assert covariance is not None and single is not None
        dt, dr = pose_error(estimate, first)
        squared.append((dt**2, dr**2))
        predicted.append((covariance.position_rms**2, covariance.rotation_rms_deg**2))
        alone.append((single.position_rms**2, single.rotation_rms_deg**2))
    ratio = np.mean(squared, axis=0) / np.mean(predicted, axis=0)
    assert np.all((ratio > 0.75) & (ratio < 1.25)), ratio
    assert np.all(np.mean(predicted, axis=0) < 0.8 * np.mean(alone, axis=0))


def _reference_views(references: list[Rigid3d], count: int) -> ReferenceViews:
    """Every reference sees each of ``count`` points; their poses known to 0.05° and 1 cm."""
    return ReferenceViews(
        point_of=np.tile(np.arange(count), len(references)),
        camera_of=np.repeat(np.arange(len(references)), count),
        rotations=np.stack([r.rotation for r in references]),
        translations=np.stack([r.translation for r in references]),
        focals=np.full(len(references), FOCAL),
        rotation_sigma_rad=np.radians(0.05),
        position_sigma=0.01,
    )


def _rig_refined(
    start: Rigid3d, frames: list[Rigid3d], xy: list[np.ndarray], points: np.ndarray
) -> Rigid3d:
    """The first frame's pose, the others fixed to it as in ``frames``, refined by pycolmap's
    generalized refinement on every observation (plain least squares at these noise levels)."""
    camera = pycolmap.Camera(model="SIMPLE_PINHOLE", width=640, height=480, params=[FOCAL, 0, 0])
    options = pycolmap.AbsolutePoseRefinementOptions()
    options.loss_function_scale = 1e3
    cams_from_rig = [
        pycolmap.Rigid3d(pycolmap.Rotation3d(p.rotation), p.translation)
        for p in (frame.compose(frames[0].inverse()) for frame in frames)
    ]
    out = pycolmap.refine_generalized_absolute_pose(
        pycolmap.Rigid3d(pycolmap.Rotation3d(start.rotation), start.translation),
        np.concatenate(xy),
        np.tile(points, (len(frames), 1)),
        np.ones(len(frames) * len(points), bool),
        np.repeat(np.arange(len(frames)), len(points)).tolist(),
        cams_from_rig,
        [camera] * len(frames),
        options,
    )
    assert out is not None
    rig = out["rig_from_world"]
    return Rigid3d(rig.rotation.matrix(), rig.translation)


def test_points_two_frames_see_are_covered_with_the_references_errors() -> None:
    """Two references 1 m apart side by side, two frames 20 cm apart 1 m ahead of them, 150
    points 5–15 m away that all four see. The references' poses are off by 0.05° and 1 cm per
    axis, the points triangulated (OpenCV) at the poses the map holds, the rig refined on them
    at 0.2 px pixel noise: over 150 trials the covariance that takes each point once, with
    both frames' observations and the references' spread, predicts the mean squared position
    error within a factor of three (2.0 cm RMS actual, 1.3 cm predicted: it is the
    covariance of the pose and the points estimated together, and the rig's refinement holds
    the points where the references placed them), no wider than one frame's; the one that
    takes the points as exact predicts under a tenth of it."""
    references = [Rigid3d(np.eye(3), np.array([x, 0.0, 0.0])) for x in (0.5, -0.5)]  # C = −t
    frames = [Rigid3d(np.eye(3), np.array([x, 0.0, -1.0])) for x in (0.1, -0.1)]
    rng = np.random.default_rng(7)
    candidates = np.column_stack(
        [rng.uniform(-6, 6, 2000), rng.uniform(-3, 3, 2000), rng.uniform(5, 15, 2000)]
    )
    inside = np.ones(len(candidates), bool)
    for pose in [*references, *frames]:
        xy = _project(pose, candidates)
        inside &= (np.abs(xy[:, 0]) < 300) & (np.abs(xy[:, 1]) < 220)
    points = candidates[inside][:150]
    seen_exact = [_project(pose, points) for pose in references]
    frames_exact = [_project(pose, points) for pose in frames]
    sigma_deg, sigma_m = 0.05, 0.01
    squared, counted, alone, exact_points = [], [], [], []
    for _ in range(150):
        held = [
            _perturbed(
                r,
                np.concatenate(
                    [rng.normal(0, np.radians(sigma_deg), 3), rng.normal(0, sigma_m, 3)]
                ),
            )
            for r in references
        ]
        seen = [xy + rng.normal(0.0, 0.2, xy.shape) for xy in seen_exact]
        projections = [np.hstack([p.rotation, p.translation[:, None]]) for p in held]
        homogeneous = cv2.triangulatePoints(*projections, (seen[0] / FOCAL).T, (seen[1] / FOCAL).T)
        triangulated = (homogeneous[:3] / homogeneous[3]).T
        xy = [e + rng.normal(0.0, 0.2, e.shape) for e in frames_exact]
        estimate = _rig_refined(frames[0], frames, xy, triangulated)
        poses = [frame.compose(frames[0].inverse()).compose(estimate) for frame in frames]
        observed = RigObservations(
            poses,
            np.full(2, FOCAL),
            np.repeat([0, 1], 150),
            np.tile(np.arange(150), 2),
            np.concatenate(xy),
            triangulated,
        )
        spread = _reference_views(held, 150)
        full = rig_pose_covariance(observed, spread)
        first = rig_pose_covariance(
            RigObservations(
                poses[:1],
                np.full(1, FOCAL),
                np.zeros(150, int),
                np.arange(150),
                xy[0],
                triangulated,
            ),
            spread,
        )
        given = rig_pose_covariance(observed)
        assert full is not None and first is not None and given is not None
        squared.append(pose_error(estimate, frames[0])[0] ** 2)
        counted.append(full.position_rms**2)
        alone.append(first.position_rms**2)
        exact_points.append(given.position_rms**2)
    ratio = np.mean(squared) / np.mean(counted)
    assert 1.0 < ratio < 3.0, ratio
    assert np.mean(counted) <= np.mean(alone)
    assert np.mean(exact_points) < np.mean(squared) / 10
