"""The 3-point-with-depth relative pose solver: exact on noise-free data, and on par with
PoseLib's 5-point LO-RANSAC on noisy data."""

from __future__ import annotations

import cv2
import numpy as np
import poselib
import pytest

from services.estimators.depth_relative_pose import (
    polish_relative_pose,
    ransac_relative_pose_depth,
)
from services.estimators.options import RansacOptions
from services.estimators.poselib_bridge import from_poselib
from services.estimators.ransac import Deadline
from services.estimators.solvers import relative_pose_3pt_depth
from services.geometry.depth_pose import sampson_errors
from services.geometry.projection import normalized_from_pixels
from services.geometry.rigid import rotation_error_deg
from tools.synthetic.correspondences import make_correspondences


def _random_rotations(rng: np.random.Generator, n: int, max_deg: float) -> np.ndarray:
    return np.stack(
        [cv2.Rodrigues(np.radians(rng.uniform(-max_deg, max_deg, 3)))[0] for _ in range(n)]
    )


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = (a * b).sum(-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.asarray(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


@pytest.mark.parametrize("with_scale", [True, False])
def test_minimal_solver_is_exact(with_scale: bool) -> None:
    rng = np.random.default_rng(0)
    B = 200
    R = _random_rotations(rng, B, 30.0)
    t = rng.normal(size=(B, 3))
    P_src = rng.uniform([-2, -2, 3], [2, 2, 8], (B, 3, 3))  # 3 points per sample, source frame
    P_dst = np.einsum("bij,bnj->bni", R, P_src) + t[:, None]
    keep = P_dst[..., 2].min(axis=1) > 0.5
    R, t, P_src, P_dst = R[keep], t[keep], P_src[keep], P_dst[keep]
    x_src, d_src = P_src[..., :2] / P_src[..., 2:], P_src[..., 2]
    x_dst, d_dst = P_dst[..., :2] / P_dst[..., 2:], P_dst[..., 2]
    if with_scale:  # depths known only up to one unknown scale per image
        scale_src = rng.uniform(0.2, 5.0, (R.shape[0], 1))
        scale_dst = rng.uniform(0.2, 5.0, (R.shape[0], 1))
        d_src, d_dst = d_src * scale_src, d_dst * scale_dst
    R_est, t_est, s_est = relative_pose_3pt_depth(x_src, d_src, x_dst, d_dst, with_scale)
    assert np.abs(R_est - R).max() < 1e-6
    if with_scale:
        unit = t / np.linalg.norm(t, axis=1, keepdims=True)
        unit_est = t_est / np.linalg.norm(t_est, axis=1, keepdims=True)
        assert np.abs(unit_est - unit).max() < 1e-6
        np.testing.assert_allclose(s_est, (scale_dst / scale_src)[:, 0], rtol=1e-6)
    else:
        assert np.abs(t_est - t).max() < 1e-6
        np.testing.assert_allclose(s_est, 1.0)


def test_sampson_error_vanishes_on_exact_correspondences() -> None:
    rng = np.random.default_rng(1)
    R = _random_rotations(rng, 1, 20.0)
    t = rng.normal(size=(1, 3))
    X = rng.uniform([-2, -2, 4], [2, 2, 8], (50, 3))
    Y = X @ R[0].T + t[0]
    err = sampson_errors(R, t, X[:, :2] / X[:, 2:], Y[:, :2] / Y[:, 2:])
    assert err.max() < 1e-12
    wrong = sampson_errors(R, t, X[:, :2] / X[:, 2:], Y[::-1, :2] / Y[::-1, 2:])
    assert np.median(wrong) > 1e-3


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_3pt_depth_on_par_with_poselib_5pt(seed: int) -> None:
    """Noisy pair (1 px, 30 % outliers, 1 % depth noise): both recover the relative pose, and
    the 3-point solver's errors are within a small margin of PoseLib's 5-point LO-RANSAC."""
    data = make_correspondences(
        seed=seed, num_references=1, matches_per_reference=400, with_depth=True
    )
    ref, cam = data.references[0], data.query_camera
    assert ref.reference_depth is not None and ref.query_depth is not None
    truth = data.query_pose.compose(ref.cam_from_world.inverse())  # query_from_ref
    ransac = {"max_epipolar_error": 2.0, "min_iterations": 200, "max_iterations": 2000, "seed": 0}
    pose5, _ = poselib.estimate_relative_pose(
        ref.reference_xy, ref.query_xy, ref.camera.to_poselib(), cam.to_poselib(), ransac, {}
    )
    five = from_poselib(pose5)
    model = ransac_relative_pose_depth(
        normalized_from_pixels(ref.camera, ref.reference_xy),
        ref.reference_depth,
        normalized_from_pixels(cam, ref.query_xy),
        ref.query_depth,
        2.0 / 500.0,
        RansacOptions(min_iterations=200, max_iterations=2000),
        np.random.default_rng(0),
        Deadline(None),
    )
    assert model is not None
    x_ref = normalized_from_pixels(ref.camera, ref.reference_xy)
    x_query = normalized_from_pixels(cam, ref.query_xy)
    three, inliers = polish_relative_pose(
        model, ref.reference_xy, ref.query_xy, x_ref, x_query, ref.camera, cam, 2.0 / 500, 500.0
    )
    rot5 = rotation_error_deg(five.rotation, truth.rotation)
    rot3 = rotation_error_deg(three.rotation, truth.rotation)
    dir5 = float(_angle_deg(five.translation, truth.translation))
    dir3 = float(_angle_deg(three.translation, truth.translation))
    assert rot5 < 0.5 and rot3 < 0.5
    # on par, not identical: the Sampson refinement can settle in a nearby minimum (seen:
    # 0.21° vs 0.08° on seed 2), so the bound is an absolute margin
    assert rot3 <= rot5 + 0.25
    assert dir3 <= dir5 + 2.0
    true_inliers = data.inlier_masks[0]
    assert inliers[true_inliers].mean() > 0.9
    assert true_inliers[inliers].mean() > 0.95
