"""First-order covariance of an absolute camera pose (and optionally its focal length) from 2D–3D
correspondences: the Gauss–Newton covariance ``σ² (JᵀJ)⁻¹`` of the reprojection least-squares
problem at the given pose, with the pixel noise σ² estimated from the residuals
(``Σ r² / (2N − p)``, p the number of parameters).

Parameters: a rotation perturbation ``δθ`` (radians, ``R = exp([δθ]×) R₀``: the angle of the
rotation error is ``|δθ|``), the camera centre ``C`` (world units) and, with ``with_focal``,
the focal length ``f`` (pixels).

Without ``references`` the points are treated as exact: the covariance describes the pose
given the points. With them, each point carries the uncertainty of its own triangulation (the
references' observations of it) and the covariance is that of the pose with the points
estimated jointly: the points are eliminated by their Schur complement. Points triangulated
from references close together seen from far away are poorly placed along their rays, and so
is a pose resting on them. The pixel noise is still the query residuals', which already carry
the points' errors: the points' errors count twice, and the covariance is conservative (on
synthetic scenes of such points the predicted RMS position error is about twice the actual
one; taking the points as exact predicts a sixth of it).

The references' own poses are known only so well (a survey's, an SfM model's, a GNSS/INS
track's errors): with a prior spread on them (``ReferenceViews.rotation_sigma_rad``,
``position_sigma``) each reference's pose is a parameter too, eliminated with the points. A
reference turned by a twentieth of a degree moves every point it saw the same way, an error
no count of points averages out; points seen tens of metres away under a fraction of a degree
magnify it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from services.geometry.rigid import Rigid3d
from services.types import BoolArray, FloatArray, IntArray


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


def projection_jacobian(X_cam: FloatArray, focal: float | FloatArray) -> FloatArray:
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


def over_pose(d_proj: FloatArray, X_cam: FloatArray, rotation: FloatArray) -> FloatArray:
    """(N, 2, 6) the projections' Jacobian over the observing camera's ``(δθ, C)``, from
    ``d_proj`` = ∂(u, v)/∂X_cam (``projection_jacobian``): ``X_cam = exp([δθ]×) R (X − C)``
    gives ``∂X_cam/∂δθ = −[X_cam]×`` and ``∂X_cam/∂C = −R`` (``rotation``: one, or one per
    point)."""
    return np.concatenate([d_proj @ -_skew(X_cam), d_proj @ -rotation], axis=2)


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
    d_proj = projection_jacobian(X_cam, focal)
    blocks = [over_pose(d_proj, X_cam, R)]
    if with_focal:
        blocks.append(np.stack([x, y], axis=1)[:, :, None])
    jacobian = np.concatenate(blocks, axis=2).reshape(2 * n, -1)
    return projected, jacobian


# the references whose pose errors the covariance counts, those that observe the most points:
# a query rests on its top-k retrieved references (10 by default); bounds the cost with many
MAX_UNCERTAIN_REFERENCES = 10


@dataclass(frozen=True)
class ReferenceViews:
    """The references' observations of the points and how well their poses are known.

    Attributes:
        point_of: (K,) the point each observation is of.
        camera_of: (K,) the reference camera that made it.
        rotations: (C, 3, 3) each reference camera's ``cam_from_world`` rotation.
        translations: (C, 3) its translation.
        focals: (C,) its focal length, pixels.
        rotation_sigma_rad: the standard deviation of each reference's rotation error about
            each axis, radians (0: the rotations are exact).
        position_sigma: the same for each reference's camera centre along each axis, map units.
    """

    point_of: IntArray
    camera_of: IntArray
    rotations: FloatArray
    translations: FloatArray
    focals: FloatArray
    rotation_sigma_rad: float = 0.0
    position_sigma: float = 0.0

    @property
    def poses_uncertain(self) -> bool:
        """Whether the references' poses are parameters (both spreads positive)."""
        return self.rotation_sigma_rad > 0.0 and self.position_sigma > 0.0


def pose_covariance(
    cam_from_world: Rigid3d,
    points3d: FloatArray,
    centered_xy: FloatArray,
    focal: float,
    with_focal: bool = False,
    references: ReferenceViews | None = None,
) -> PoseCovariance | None:
    """Covariance of the pose (and focal) at ``cam_from_world``.

    Args:
        points3d: (N, 3) world points.
        centered_xy: (N, 2) observed pixels minus the principal point (undistorted).
        focal: focal length, pixels.
        with_focal: the focal length is a free parameter too.
        references: the references' observations of the points (``point_of`` indexes
            ``points3d``) and their poses' spread; None: the points are exact.
    Returns:
        ``PoseCovariance``; None with too few points in front of the camera for the parameters
        or a singular system.
    """
    in_front = cam_from_world.apply(points3d)[:, 2] > 1e-9
    p = 7 if with_focal else 6
    n = int(in_front.sum())
    if 2 * n <= p + 1:
        return None
    projected, jacobian = reprojection_jacobian(
        cam_from_world, points3d[in_front], focal, with_focal
    )
    residuals = (projected - centered_xy[in_front]).reshape(-1)
    # the noise from the query's residuals, which carry the points' errors too: applied to
    # the references' observations as well, it counts the points' errors twice (conservative)
    sigma2 = float(residuals @ residuals) / (2 * n - p)
    if references is None:
        normal = jacobian.T @ jacobian
    else:
        normal, uncertain = _pose_information(
            jacobian.reshape(n, 2, p), points3d[in_front], _observing(references, in_front)
        )
        normal = _with_prior(normal, p, len(uncertain), references, sigma2)
    return _covariance(normal, p, sigma2, n)


def _observing(references: ReferenceViews, kept: BoolArray) -> ReferenceViews:
    """``references``' observations of the ``kept`` points, indexed among them."""
    index_of = np.cumsum(kept) - 1
    seen = kept[references.point_of]
    return replace(
        references,
        point_of=index_of[references.point_of[seen]],
        camera_of=references.camera_of[seen],
    )


def _covariance(normal: FloatArray, p: int, sigma2: float, n: int) -> PoseCovariance | None:
    """The first ``p`` parameters' covariance from the information ``normal`` in units of the
    pixel noise ``sigma2``; None when it is singular."""
    # scale the parameters to unit diagonal before inverting: radians, metres and pixels differ
    scale = 1.0 / np.sqrt(np.maximum(np.diag(normal), np.finfo(np.float64).tiny))
    scaled = normal * scale[:, None] * scale[None, :]
    if not np.all(np.isfinite(scaled)) or np.linalg.cond(scaled) > 1e12:
        return None
    covariance = np.linalg.inv(scaled) * scale[:, None] * scale[None, :] * sigma2
    return PoseCovariance(covariance[:p, :p], float(np.sqrt(sigma2)), n)


def _with_prior(
    normal: FloatArray, p: int, count: int, references: ReferenceViews, sigma2: float
) -> FloatArray:
    """``normal`` with the references' prior, ``σ² / σ_ref²`` in units of the pixel noise, on
    the ``count`` reference blocks that follow the first ``p`` parameters: it keeps the system
    determined."""
    if count == 0:
        return normal
    prior = sigma2 / np.repeat([references.rotation_sigma_rad, references.position_sigma], 3) ** 2
    normal = normal.copy()
    diagonal = np.arange(p, p + 6 * count)
    normal[diagonal, diagonal] += np.tile(prior, count)
    return normal


def _pose_information(
    query_jacobian: FloatArray,
    points3d: FloatArray,
    references: ReferenceViews,
    query_point_of: IntArray | None = None,
) -> tuple[FloatArray, IntArray]:
    """The information, in units of the pixel noise, on the query's parameters and (when their
    poses are uncertain) the ``(δθ, C)`` of the ``MAX_UNCERTAIN_REFERENCES`` references that
    observe the most points after eliminating the points: ``S = H_pp − Σ_i H_pi H_ii⁻¹ H_ip``
    over the points i, each point's ``H_ii`` its query observations' ``Bᵀ B`` plus its
    reference observations', with ``B = −J[:, 3:6]`` a query projection's Jacobian over the
    point (``∂X_cam/∂X = −∂X_cam/∂C``, the observing camera's centre). The query's parameters
    come first, then those references', in the order of the references returned (indices of
    ``references``' cameras), without their prior (``_with_prior``); the other references'
    poses are taken as exact. A point whose ``H_ii`` is singular (the references do not
    constrain it) is left out with all its observations.

    Args:
        query_jacobian: (Q, 2, p) each query observation's projection Jacobian.
        points3d: (N, 3) the points, in front of the cameras that observe them.
        references: the references' observations of them (``point_of`` indexes ``points3d``).
        query_point_of: (Q,) the point each query observation is of (the cameras of a rig may
            observe one point several times); None: the i-th observes point i.
    """
    n, p = len(points3d), query_jacobian.shape[2]
    point_of, camera_of = references.point_of, references.camera_of
    rotations = references.rotations[camera_of]
    X_cam = np.einsum("kij,kj->ki", rotations, points3d[point_of])
    X_cam += references.translations[camera_of]
    front = X_cam[:, 2] > 1e-9
    X_cam[~front, 2] = 1.0  # no information: zeroed below
    d_proj = projection_jacobian(X_cam, references.focals[camera_of]) * front[:, None, None]
    over_point = d_proj @ rotations  # ∂X_cam/∂X = R
    if query_point_of is None:
        query_point_of = np.arange(n)
    b = -query_jacobian[:, :, 3:6]
    point_information = sum_by(query_point_of, np.swapaxes(b, 1, 2) @ b, n)
    point_information += sum_by(point_of, np.swapaxes(over_point, 1, 2) @ over_point, n)
    inverse, solvable = inverse_3x3(point_information)
    uncertain = np.zeros(0, np.int64)
    if references.poses_uncertain:
        kept = solvable[point_of]
        observed = np.bincount(camera_of[kept], minlength=len(references.rotations))
        uncertain = np.argsort(-observed, kind="stable")[:MAX_UNCERTAIN_REFERENCES]
        uncertain = uncertain[observed[uncertain] > 0]
    size = p + 6 * len(uncertain)
    normal = np.zeros((size, size))
    used = query_jacobian[solvable[query_point_of]]
    normal[:p, :p] = np.einsum("nai,naj->ij", used, used)
    coupling = np.zeros((n, size, 3))  # H_pi: each parameter against each point
    coupling[:, :p] = sum_by(query_point_of, np.swapaxes(query_jacobian, 1, 2) @ b, n)
    if len(uncertain):
        slot = np.full(len(references.rotations), -1, np.int64)
        slot[uncertain] = np.arange(len(uncertain))
        rows = np.flatnonzero((slot[camera_of] >= 0) & solvable[point_of])
        slot_of, point_of = slot[camera_of[rows]], point_of[rows]
        over_reference = over_pose(d_proj[rows], X_cam[rows], rotations[rows])
        blocks = sum_by(slot_of, np.swapaxes(over_reference, 1, 2) @ over_reference, len(uncertain))
        for c in range(len(uncertain)):
            block = slice(p + 6 * c, p + 6 * c + 6)
            normal[block, block] = blocks[c]
        # a reference observes a point once: each (point, slot) pair is its own entry
        per_observation = np.swapaxes(over_reference, 1, 2) @ over_point[rows]  # (K, 6, 3)
        flat = coupling.reshape(n * size, 3)
        targets = (point_of * size + p + 6 * slot_of)[:, None] + np.arange(6)
        flat += sum_by(targets.reshape(-1), per_observation.reshape(-1, 1, 3), n * size)[:, 0]
    coupling = coupling[solvable]
    normal -= np.tensordot(coupling @ inverse[solvable], coupling, axes=([0, 2], [0, 2]))
    return normal, uncertain


def sum_by(index: IntArray, values: FloatArray, count: int) -> FloatArray:
    """(K, a, b) values summed by ``index`` into (count, a, b) (``np.bincount`` per entry: far
    faster than ``np.add.at``)."""
    flat = values.reshape(len(values), -1)
    sums = [np.bincount(index, weights=flat[:, j], minlength=count) for j in range(flat.shape[1])]
    return np.stack(sums, axis=1).astype(np.float64).reshape(count, *values.shape[1:])


def inverse_3x3(matrices: FloatArray) -> tuple[FloatArray, BoolArray]:
    """(N, 3, 3) symmetric matrices → their inverses by the adjugate (far cheaper than a
    batched solve) and which are solvable: a determinant below 1e-12 of the diagonal's product
    is singular (its inverse left zero)."""
    adjugate = np.cross(matrices[:, [1, 2, 0]], matrices[:, [2, 0, 1]])  # rows: cofactors
    determinant = np.einsum("ni,ni->n", matrices[:, 0], adjugate[:, 0])
    scale = np.prod(np.abs(np.diagonal(matrices, axis1=1, axis2=2)), axis=1)
    solvable = determinant > 1e-12 * scale
    inverse = adjugate / np.where(solvable, determinant, 1.0)[:, None, None]
    inverse[~solvable] = 0.0
    return inverse, solvable


def rig_adjoint(first: Rigid3d, other: Rigid3d) -> FloatArray:
    """(6, 6) ``∂(δθ, C)_other / ∂(δθ, C)_first`` for two cameras fixed to each other: with
    ``R_o = R_of R_f`` and ``C_o = C_f + R_fᵀ d`` (``d`` the other centre in the first camera's
    frame), turning the first by ``δθ`` turns the other by ``R_of δθ`` and moves its centre by
    ``R_fᵀ [d]× δθ``; moving the first's centre moves the other's alike."""
    rotation = first.rotation
    adjoint = np.eye(6)
    adjoint[:3, :3] = other.rotation @ rotation.T
    offset = rotation @ (other.center - first.center)
    adjoint[3:, :3] = rotation.T @ _skew(offset[None])[0]
    return adjoint


@dataclass(frozen=True)
class RigObservations:
    """What the cameras of a rig observe.

    Attributes:
        poses: each camera's ``cam_from_world``.
        focals: (V,) each camera's focal length, pixels.
        view_of: (Q,) the camera of each observation.
        point_of: (Q,) the point it is of.
        centered_xy: (Q, 2) the observed pixel, undistorted, minus its camera's principal point.
        points3d: (N, 3) the world points; one point whichever cameras observe it.
    """

    poses: list[Rigid3d]
    focals: FloatArray
    view_of: IntArray
    point_of: IntArray
    centered_xy: FloatArray
    points3d: FloatArray


def rig_pose_covariance(
    observed: RigObservations, references: ReferenceViews | None = None
) -> PoseCovariance | None:
    """Covariance of the first camera's pose ``(δθ, C)`` when all cameras move together (their
    relative poses exact, as an AR session's over a few frames): every camera's projection
    Jacobian carried onto the first camera's parameters by ``rig_adjoint``, the pixel noise
    pooled over all observations. Without ``references`` the points are exact (with one
    camera it is ``pose_covariance``'s); with them, the points are eliminated as in
    ``pose_covariance``, a point that several cameras observe once with all its observations
    (the cameras' and the references'), a reference once with its prior. As for one camera,
    this is the covariance of the pose and the points estimated together; a pose estimated on
    points the references alone triangulated varies more (on a synthetic rig whose references'
    pose errors dominate, 2.0 cm RMS against 1.3 cm predicted; the tests).

    Returns:
        ``PoseCovariance`` (``num_points``: observations in front of their cameras); None with
        too few of them or a singular system.
    """
    first = observed.poses[0]
    X_cam = np.zeros((len(observed.view_of), 3))
    jacobian = np.zeros((len(observed.view_of), 2, 6))
    for v, pose in enumerate(observed.poses):
        rows = np.flatnonzero(observed.view_of == v)
        X_cam[rows] = pose.apply(observed.points3d[observed.point_of[rows]])
        d_proj = projection_jacobian(X_cam[rows], float(observed.focals[v]))
        jacobian[rows] = over_pose(d_proj, X_cam[rows], pose.rotation) @ rig_adjoint(first, pose)
    in_front = X_cam[:, 2] > 1e-9
    q = int(in_front.sum())
    if 2 * q <= 7:
        return None
    X_cam, jacobian = X_cam[in_front], jacobian[in_front]
    focal = observed.focals[observed.view_of[in_front]][:, None]
    residuals = (focal * X_cam[:, :2] / X_cam[:, 2:] - observed.centered_xy[in_front]).reshape(-1)
    sigma2 = float(residuals @ residuals) / (2 * q - 6)
    if references is None:
        normal = np.einsum("nai,naj->ij", jacobian, jacobian)
        return _covariance(normal, 6, sigma2, q)
    kept = np.zeros(len(observed.points3d), bool)
    kept[observed.point_of[in_front]] = True
    index_of = np.cumsum(kept) - 1
    normal, uncertain = _pose_information(
        jacobian,
        observed.points3d[kept],
        _observing(references, kept),
        index_of[observed.point_of[in_front]],
    )
    normal = _with_prior(normal, 6, len(uncertain), references, sigma2)
    return _covariance(normal, 6, sigma2, q)
