"""First-order covariance of an absolute camera pose (and optionally its focal length) from 2D–3D
correspondences: the Gauss–Newton covariance ``σ² (JᵀJ)⁻¹`` of the reprojection least-squares
problem at the given pose, with the pixel noise σ² estimated from the residuals
(``Σ r² / (2N − p)``, p the number of parameters).

Parameters: a rotation perturbation ``δθ`` (radians, ``R = exp([δθ]×) R₀``: the angle of the
rotation error is ``|δθ|``), the camera centre ``C`` (world units) and, with ``with_focal``,
the focal length ``f`` (pixels).

Without ``point_information`` the points are treated as exact: the covariance describes the pose
given the points. With it, each point carries the uncertainty of its own triangulation (the
information its reference observations give, ``reference_point_information``) and the
covariance is that of the pose with the points estimated jointly: the points are eliminated by
their Schur complement. Points triangulated from references close together seen from far away
are poorly placed along their rays, and so is a pose resting on them. The pixel noise is still
the query residuals', which already carry the points' errors: the points' errors count twice,
and the covariance is conservative (on synthetic scenes of such points the predicted RMS
position error is about twice the actual one; taking the points as exact predicts a sixth of
it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.geometry.rigid import Rigid3d
from services.types import FloatArray, IntArray


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


def _projection_jacobian(X_cam: FloatArray, focal: float | FloatArray) -> FloatArray:
    """(N, 2, 3) ``∂(u, v)/∂X_cam`` of the projections ``f · (x/z, y/z)`` of camera-frame
    points (``focal``: one for all, or one per point)."""
    z = X_cam[:, 2]
    d_proj = np.zeros((X_cam.shape[0], 2, 3))
    d_proj[:, 0, 0] = d_proj[:, 1, 1] = focal / z
    d_proj[:, 0, 2] = -focal * X_cam[:, 0] / z**2
    d_proj[:, 1, 2] = -focal * X_cam[:, 1] / z**2
    return d_proj


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
    d_proj = _projection_jacobian(X_cam, focal)
    d_theta = d_proj @ -_skew(X_cam)  # X_cam = exp([δθ]×) R (X − C): ∂X_cam/∂δθ = −[X_cam]×
    d_center = d_proj @ -R  # ∂X_cam/∂C = −R
    blocks = [d_theta, d_center]
    if with_focal:
        blocks.append(np.stack([x, y], axis=1)[:, :, None])
    jacobian = np.concatenate(blocks, axis=2).reshape(2 * n, -1)
    return projected, jacobian


def reference_point_information(
    points3d: FloatArray,
    point_of: IntArray,
    rotations: FloatArray,
    translations: FloatArray,
    focals: FloatArray,
) -> FloatArray:
    """The information each point's reference observations give about it, ``Σ_k A_kᵀ A_k``
    with ``A_k`` the Jacobian of observation k's pixel projection over the point (units of
    pixel noise: divide by σ² for the inverse covariance).

    Args:
        points3d: (T, 3) world points.
        point_of: (K,) the point each observation is of.
        rotations: (K, 3, 3) ``cam_from_world`` rotation of the observing camera.
        translations: (K, 3) its translation.
        focals: (K,) its focal length, pixels.
    Returns:
        (T, 3, 3); zero for a point no observation sees (or none in front).
    """
    X_cam = np.einsum("kij,kj->ki", rotations, points3d[point_of]) + translations
    front = X_cam[:, 2] > 1e-9
    X_cam[~front, 2] = 1.0  # no information: zeroed below
    d_proj = _projection_jacobian(X_cam, focals)
    jacobian = (d_proj @ rotations) * front[:, None, None]  # ∂X_cam/∂X = R
    per_observation = (np.swapaxes(jacobian, 1, 2) @ jacobian).reshape(-1, 9)
    count = points3d.shape[0]
    sums = [np.bincount(point_of, weights=per_observation[:, j], minlength=count) for j in range(9)]
    information = np.stack(sums, axis=1).astype(np.float64).reshape(count, 3, 3)
    return information


def pose_covariance(
    cam_from_world: Rigid3d,
    points3d: FloatArray,
    centered_xy: FloatArray,
    focal: float,
    with_focal: bool = False,
    point_information: FloatArray | None = None,
) -> PoseCovariance | None:
    """Covariance of the pose (and focal) at ``cam_from_world``.

    Args:
        points3d: (N, 3) world points.
        centered_xy: (N, 2) observed pixels minus the principal point (undistorted).
        focal: focal length, pixels.
        with_focal: the focal length is a free parameter too.
        point_information: (N, 3, 3) what each point's own observations tell of it
            (``reference_point_information``); None: the points are exact.
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
    # the noise from the query's residuals, which carry the points' errors too: applied to
    # the references' observations as well, it counts the points' errors twice (conservative)
    sigma2 = float(residuals @ residuals) / (2 * n - p)
    if point_information is None:
        normal = jacobian.T @ jacobian
    else:
        per_point = jacobian.reshape(n, 2, p)
        weighted = _observation_weights(per_point, point_information[in_front]) @ per_point
        normal = np.tensordot(per_point, weighted, axes=([0, 1], [0, 1]))
    # scale the parameters to unit diagonal before inverting: radians, metres and pixels differ
    scale = 1.0 / np.sqrt(np.maximum(np.diag(normal), np.finfo(np.float64).tiny))
    scaled = normal * scale[:, None] * scale[None, :]
    if not np.all(np.isfinite(scaled)) or np.linalg.cond(scaled) > 1e12:
        return None
    covariance = np.linalg.inv(scaled) * scale[:, None] * scale[None, :] * sigma2
    return PoseCovariance(covariance, float(np.sqrt(sigma2)), n)


def _observation_weights(jacobian: FloatArray, point_information: FloatArray) -> FloatArray:
    """(N, 2, 2) ``W_i = (I + B_i I_i⁻¹ B_iᵀ)⁻¹ = I − B_i (B_iᵀ B_i + I_i)⁻¹ B_iᵀ``: the inverse
    covariance, in units of the pixel noise, of point i's query observation once the point's
    own error is counted, with ``B_i = −J_i[:, 3:6]`` the Jacobian of its projection over the
    point (``∂X_cam/∂X = −∂X_cam/∂C``) and ``I_i`` its information from the references. The
    pose's information is ``Σ J_iᵀ W_i J_i``: the points eliminated by their Schur complement.
    A point the references do not constrain gives nothing (``W_i = 0``)."""
    b = -jacobian[:, :, 3:6]  # (N, 2, 3)
    bt = np.swapaxes(b, 1, 2)
    joint = bt @ b + point_information  # (N, 3, 3), symmetric
    # the inverse by the adjugate (3 × 3 blocks: far cheaper than a batched solve); a
    # determinant below 1e-12 of the diagonal's product is singular
    adjugate = np.cross(joint[:, [1, 2, 0]], joint[:, [2, 0, 1]])  # rows: cofactors (symmetric)
    determinant = np.einsum("ni,ni->n", joint[:, 0], adjugate[:, 0])
    scale = np.prod(np.abs(np.diagonal(joint, axis1=1, axis2=2)), axis=1)
    solvable = determinant > 1e-12 * scale
    inverse = adjugate / np.where(solvable, determinant, 1.0)[:, None, None]
    weights: FloatArray = np.eye(2) - b @ inverse @ bt
    weights[~solvable] = 0.0
    return weights
