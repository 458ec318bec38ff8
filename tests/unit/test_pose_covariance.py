"""The pose covariance: its Jacobian against finite differences, and its predicted spread against
the actual spread of least-squares poses (pycolmap refinement) over many noisy trials."""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap
import pytest

from services.geometry.camera import Camera
from services.geometry.pose_covariance import pose_covariance, reprojection_jacobian
from services.geometry.rigid import Rigid3d, pose_error
from tools.synthetic.correspondences import sample_room_points

CAMERA = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))


def _pose() -> Rigid3d:
    R = cv2.Rodrigues(np.array([0.05, -0.1, 0.02]))[0]
    return Rigid3d(R, -R @ np.array([0.4, 0.2, -1.0]))


def _visible_points(pose: Rigid3d, count: int, seed: int) -> np.ndarray:
    points = sample_room_points(np.random.default_rng(seed), 20 * count)
    X = pose.apply(points)
    xy = X[:, :2] / X[:, 2:] * 500.0
    keep = (X[:, 2] > 0.5) & (np.abs(xy[:, 0]) < 320) & (np.abs(xy[:, 1]) < 240)
    return points[keep][:count]


def _perturbed(pose: Rigid3d, delta: np.ndarray) -> Rigid3d:
    R = cv2.Rodrigues(delta[:3])[0] @ pose.rotation
    return Rigid3d(R, -R @ (pose.center + delta[3:6]))


def test_jacobian_matches_finite_differences() -> None:
    pose = _pose()
    points = _visible_points(pose, 50, 0)
    focal = 500.0
    _, jacobian = reprojection_jacobian(pose, points, focal, with_focal=True)
    step = 1e-6
    for k in range(7):
        delta = np.zeros(7)
        delta[k] = step
        plus = reprojection_jacobian(_perturbed(pose, delta), points, focal + delta[6], True)[0]
        minus = reprojection_jacobian(_perturbed(pose, -delta), points, focal - delta[6], True)[0]
        numeric = ((plus - minus) / (2 * step)).reshape(-1)
        np.testing.assert_allclose(jacobian[:, k], numeric, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("with_focal", [False, True])
def test_predicted_spread_matches_the_actual_spread(with_focal: bool) -> None:
    """Over 200 trials of 1.5 px noise, the mean squared error of the refined pose matches the
    predicted ``trace Σ`` (position and rotation) within 25 %, and the error is within 3 ×
    the predicted RMS in ≥ 95 % of the trials."""
    truth = _pose()
    points = _visible_points(truth, 80, 1)
    exact = truth.apply(points)
    exact_xy = exact[:, :2] / exact[:, 2:] * 500.0 + [320.0, 240.0]
    rng = np.random.default_rng(2)
    options = pycolmap.AbsolutePoseRefinementOptions()
    options.refine_focal_length = with_focal
    options.loss_function_scale = 1e3  # Cauchy at 1000 px: plain least squares at 1.5 px noise
    squared, predicted, within = [], [], []
    for _ in range(200):
        xy = exact_xy + rng.normal(0.0, 1.5, exact_xy.shape)
        camera = pycolmap.Camera(
            model="SIMPLE_PINHOLE", width=640, height=480, params=[500.0, 320.0, 240.0]
        )
        out = pycolmap.refine_absolute_pose(
            pycolmap.Rigid3d(pycolmap.Rotation3d(truth.rotation), truth.translation),
            xy,
            points,
            np.ones(len(xy), bool),
            camera,
            options,
        )
        estimate = Rigid3d(
            out["cam_from_world"].rotation.matrix(), out["cam_from_world"].translation
        )
        focal = float(camera.params[0])
        covariance = pose_covariance(estimate, points, xy - [320.0, 240.0], focal, with_focal)
        assert covariance is not None
        dt, dr = pose_error(estimate, truth)
        squared.append((dt**2, dr**2))
        predicted.append((covariance.position_rms**2, covariance.rotation_rms_deg**2))
        within.append((dt < 3 * covariance.position_rms, dr < 3 * covariance.rotation_rms_deg))
    ratio = np.mean(squared, axis=0) / np.mean(predicted, axis=0)
    assert np.all((ratio > 0.75) & (ratio < 1.25)), ratio
    assert np.all(np.mean(within, axis=0) >= 0.95)


def test_too_few_points_give_no_covariance() -> None:
    pose = _pose()
    points = _visible_points(pose, 3, 3)
    X = pose.apply(points)
    assert pose_covariance(pose, points, X[:, :2] / X[:, 2:] * 500.0, 500.0, True) is None
