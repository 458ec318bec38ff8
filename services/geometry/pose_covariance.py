"""First-order covariance of an absolute camera pose (and optionally its focal length) from 2D–3D
correspondences: the Gauss–Newton covariance ``σ² (JᵀJ)⁻¹`` of the reprojection least-squares
problem at the given pose, with the pixel noise σ² estimated from the residuals
(``Σ r² / (2N − p)``, p the number of parameters).

Parameters: a rotation perturbation ``δθ`` (radians, ``R = exp([δθ]×) R₀``: the angle of the
rotation error is ``|δθ|``), the camera centre ``C`` (world units) and, with ``with_focal``,
the focal length ``f`` (pixels). Points are treated as exact, so the covariance describes the
pose given the points; errors of the points enter only through the residuals they cause.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.geometry.rigid import Rigid3d
from services.types import FloatArray


@dataclass(frozen=True)
class PoseCovariance:
    """Attributes:
    covariance: (p, p) over ``(δθ [rad], C [world units], f [px])``, p = 6 or 7.
    sigma_px: the estimated pixel noise (residual standard deviation).
    num_points: correspondences used.
    """

    covariance: FloatArray
    sigma_px: float
    num_points: int

    @property
    def rotation(self) -> FloatArray:
        """(3, 3) covariance of the rotation error vector, radians²."""
        return self.covariance[:3, :3]

    @property
    def center(self) -> FloatArray:
        """(3, 3) covariance of the camera centre, world units²."""
        return self.covariance[3:6, 3:6]

    @property
    def position_rms(self) -> float:
        """Root-mean-square camera-centre error predicted, ``sqrt(trace Σ_C)``."""
        return float(np.sqrt(max(np.trace(self.center), 0.0)))

    @property
    def rotation_rms_deg(self) -> float:
        """Root-mean-square rotation-angle error predicted, ``sqrt(trace Σ_θ)``, degrees."""
        return float(np.degrees(np.sqrt(max(np.trace(self.rotation), 0.0))))

    @property
    def focal_sigma(self) -> float | None:
        """Standard deviation of the focal length, pixels (None without it)."""
        if self.covariance.shape[0] < 7:
            return None
        return float(np.sqrt(max(self.covariance[6, 6], 0.0)))


def _skew(v: FloatArray) -> FloatArray:
    """(N, 3) → (N, 3, 3) cross-product matrices."""
    zero = np.zeros(v.shape[0])
    return np.stack(
        [
            np.stack([zero, -v[:, 2], v[:, 1]], axis=1),
            np.stack([v[:, 2], zero, -v[:, 0]], axis=1),
            np.stack([-v[:, 1], v[:, 0], zero], axis=1),
        ],
        axis=1,
    )


def reprojection_jacobian(
    cam_from_world: Rigid3d, points3d: FloatArray, focal: float, with_focal: bool
) -> tuple[FloatArray, FloatArray]:
    """Projections of world points through a pinhole camera with principal point 0 and their
    Jacobian.

    Args:
        points3d: (N, 3) world points, in front of the camera.
        focal: focal length, pixels.
    Returns:
        (N, 2) projections ``f · (x/z, y/z)`` and the (2N, p) Jacobian over
        ``(δθ, C[, f])``, rows interleaved (u₀, v₀, u₁, …).
    """
    R = cam_from_world.rotation
    X_cam = cam_from_world.apply(points3d)
    z = X_cam[:, 2]
    x, y = X_cam[:, 0] / z, X_cam[:, 1] / z
    projected = focal * np.stack([x, y], axis=1)
    n = points3d.shape[0]
    d_proj = np.zeros((n, 2, 3))  # ∂(u, v)/∂X_cam
    d_proj[:, 0, 0] = d_proj[:, 1, 1] = focal / z
    d_proj[:, 0, 2] = -focal * x / z
    d_proj[:, 1, 2] = -focal * y / z
    d_theta = d_proj @ -_skew(X_cam)  # X_cam = exp([δθ]×) R (X − C): ∂X_cam/∂δθ = −[X_cam]×
    d_center = d_proj @ -R  # ∂X_cam/∂C = −R
    blocks = [d_theta, d_center]
    if with_focal:
        blocks.append(np.stack([x, y], axis=1)[:, :, None])
    jacobian = np.concatenate(blocks, axis=2).reshape(2 * n, -1)
    return projected, jacobian


def pose_covariance(
    cam_from_world: Rigid3d,
    points3d: FloatArray,
    centered_xy: FloatArray,
    focal: float,
    with_focal: bool = False,
) -> PoseCovariance | None:
    """Covariance of the pose (and focal) at ``cam_from_world``.

    Args:
        points3d: (N, 3) world points.
        centered_xy: (N, 2) observed pixels minus the principal point (undistorted).
        focal: focal length, pixels.
        with_focal: the focal length is a free parameter too.
    Returns:
        ``PoseCovariance``; None with too few points in front of the camera for the parameters
        or a singular system.
    """
    in_front = cam_from_world.apply(points3d)[:, 2] > 1e-9
    points3d, centered_xy = points3d[in_front], centered_xy[in_front]
    p = 7 if with_focal else 6
    n = int(points3d.shape[0])
    if 2 * n <= p + 1:
        return None
    projected, jacobian = reprojection_jacobian(cam_from_world, points3d, focal, with_focal)
    residuals = (projected - centered_xy).reshape(-1)
    sigma2 = float(residuals @ residuals) / (2 * n - p)
    normal = jacobian.T @ jacobian
    # scale the parameters to unit diagonal before inverting: radians, metres and pixels differ
    scale = 1.0 / np.sqrt(np.maximum(np.diag(normal), np.finfo(np.float64).tiny))
    scaled = normal * scale[:, None] * scale[None, :]
    if not np.all(np.isfinite(scaled)) or np.linalg.cond(scaled) > 1e12:
        return None
    covariance = np.linalg.inv(scaled) * scale[:, None] * scale[None, :] * sigma2
    return PoseCovariance(covariance, float(np.sqrt(sigma2)), n)
