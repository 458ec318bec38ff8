"""Post-estimation verification of a query pose by the structure the references imply.

A robust loop over epipolar constraints (E5+1 and other structureless estimators) can always
find some consensus: with a 12 px threshold a random correspondence lies within the epipolar
band of a fitted pose often enough that an image of an unrelated scene collects dozens of
"inliers" spread over every retrieved reference. Epipolar inliers therefore do not prove the
pose.

The check here asks for 3D evidence the robust loop did not fit directly. A query keypoint
that is an inlier in two or more references gives a *track*. Its reference observations alone
(the query is left out) are triangulated into a 3D point, which must

1. reproject into each reference that observes it within that reference's threshold, with at
   least ``min_views`` agreeing reference observations (robust to wrong matches inside a track:
   every pair of a track's first ``max_pair_views`` observations proposes a point, the one most
   observations agree with wins, and the agreeing observations are re-triangulated), and
2. lie in front of the query and reproject into the query keypoint within the query's threshold.

For a correct pose most tracks pass (on redkitchen hundreds per query); for an unrelated image
the reference observations of a track are often a real scene point (references overlap), but
the query ray has no reason to pass through it, and the pose has only six degrees of freedom to
make a handful of them agree (measured: at most 3 verified points for unrelated images, 0–5 for
real queries whose pose is wrong by metres or tens of degrees).

All geometry is done with bearing vectors, so lens distortion is handled by whoever turns
pixels into normalised coordinates; angular thresholds are pixel thresholds divided by the
focal length. Pure numpy, no per-point Python loops.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from services.estimators.base import EstimateResult, FailureReason, ReferenceObservation
from services.estimators.correspondences import unique_points
from services.estimators.options import EstimatorOptions
from services.estimators.ransac import Deadline, DeadlinePassedError
from services.geometry.camera import Camera
from services.geometry.projection import normalized_from_pixels
from services.geometry.rigid import Rigid3d
from services.types import BoolArray, FloatArray, IntArray

logger = logging.getLogger(__name__)

# the stat ``verify_pose`` adds to a result it checked: its verified 3D points
VERIFIED_POINTS = "verified_points"

# Two rays closer to parallel than this (sine of their angle, ~0.006°) do not triangulate.
_MIN_SINE = 1e-4


@dataclass(frozen=True)
class StructureCheck:
    """Outcome of ``verify_by_reference_triangulation``.

    Attributes:
        correspondence_verified: (K,) bool, the correspondence belongs to a verified point and
            its reference observation agrees with that point.
        points: (T, 3) float64 world points, one per track (NaN where not triangulated).
        point_verified: (T,) bool, the track passed every check.
        num_tracks: tracks with at least ``min_views`` reference observations before checking.
    """

    correspondence_verified: BoolArray
    points: FloatArray
    point_verified: BoolArray
    num_tracks: int

    @property
    def num_verified_points(self) -> int:
        return int(self.point_verified.sum())


def _unit_rays(normalized: FloatArray) -> FloatArray:
    """(K, 2) normalised image coordinates → (K, 3) unit bearing vectors in the camera frame."""
    rays = np.concatenate([normalized, np.ones((normalized.shape[0], 1))], axis=1)
    out: FloatArray = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    return out


def _group_sum(ids: IntArray, values: FloatArray, count: int) -> FloatArray:
    """Sum rows of (K, ...) ``values`` by group id: (count, ...)."""
    flat = values.reshape(values.shape[0], -1)
    sums = np.stack(
        [np.bincount(ids, weights=flat[:, j], minlength=count) for j in range(flat.shape[1])],
        axis=1,
    )
    out: FloatArray = sums.reshape((count, *values.shape[1:]))
    return out


def _cosine_to(points: FloatArray, centers: FloatArray, rays: FloatArray) -> FloatArray:
    """Cosine of the angle between unit ``rays`` and ``points − centers`` (broadcast, (..., 3)
    → (...)); NaN where a point is NaN. Positive exactly when the point is in front."""
    to_point = points - centers
    with np.errstate(invalid="ignore", divide="ignore"):
        out: FloatArray = np.einsum("...i,...i->...", to_point, rays) / np.linalg.norm(
            to_point, axis=-1
        )
    return out


def two_ray_midpoints(c1: FloatArray, d1: FloatArray, c2: FloatArray, d2: FloatArray) -> FloatArray:
    """Midpoints of the shortest segments between rays ``c + s·d``.

    Args:
        c1, d1, c2, d2: (..., 3) centres and unit directions.
    Returns:
        (..., 3) points; NaN where the rays are (nearly) parallel.
    """
    b = np.einsum("...i,...i->...", d1, d2)
    w = c1 - c2
    e1 = np.einsum("...i,...i->...", d1, w)
    e2 = np.einsum("...i,...i->...", d2, w)
    denom = 1.0 - b * b  # sin² of the angle between the rays
    ok = denom > _MIN_SINE**2
    safe = np.where(ok, denom, 1.0)
    s1 = (b * e2 - e1) / safe
    s2 = (e2 - b * e1) / safe
    mid = 0.5 * (c1 + s1[..., None] * d1 + c2 + s2[..., None] * d2)
    out: FloatArray = np.where(ok[..., None], mid, np.nan)
    return out


def _well_conditioned(normal: FloatArray) -> BoolArray:
    """(T,) whether each (T, 3, 3) ray-intersection system Σ (I − d dᵀ) has a unique solution.

    Its eigenvalues are 0 along a direction all its rays share; for two rays at angle θ the
    smallest over the largest is about θ²/4. Agreeing rays can all be parallel (they agreed
    with a hypothesis of a pair whose other ray did not), so the system is checked, not
    assumed: tracks under the two-ray limit ``_MIN_SINE`` stay untriangulated.
    """
    finite: BoolArray = np.asarray(np.isfinite(normal).all(axis=(1, 2)))
    eig = np.linalg.eigvalsh(np.where(finite[:, None, None], normal, np.eye(3)))
    ratio = eig[:, 0] / np.maximum(eig[:, -1], np.finfo(np.float64).tiny)
    out: BoolArray = finite & (ratio > _MIN_SINE**2 / 4.0)
    return out


def _poll(deadline: Deadline | None) -> None:
    if deadline is not None:
        deadline.check()


def _robust_agreement(
    tid: IntArray,
    center: FloatArray,
    ray: FloatArray,
    cos_limit: FloatArray,
    min_views: int,
    max_pair_views: int,
    deadline: Deadline | None = None,
) -> BoolArray:
    """Per observation: agrees with its track's best two-view hypothesis.

    Args:
        tid: (K,) track of each observation, values in [0, T).
        center, ray: (K, 3) world centre and unit ray of each observation.
        cos_limit: (K,) cosine of each observation's angular threshold.
    Returns:
        (K,) bool.
    """
    k = tid.shape[0]
    counts = np.bincount(tid)
    order = np.argsort(tid, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    agrees = np.zeros(k, bool)
    # one vectorised pass per distinct track length (at most the number of references)
    for length in np.unique(counts[counts >= min_views]):
        _poll(deadline)
        tracks = np.flatnonzero(counts == length)
        obs = order[starts[tracks][:, None] + np.arange(length)]  # (T_L, L)
        first, second = np.triu_indices(min(int(length), max_pair_views), 1)  # (P,)
        hypotheses = two_ray_midpoints(
            center[obs[:, first]], ray[obs[:, first]], center[obs[:, second]], ray[obs[:, second]]
        )  # (T_L, P, 3)
        cosine = _cosine_to(
            hypotheses[:, :, None, :], center[obs][:, None], ray[obs][:, None]
        )  # (T_L, P, L)
        ok = cosine > cos_limit[obs][:, None, :]
        # most agreeing observations; ties broken by the smaller summed angular error
        score = ok.sum(axis=2) + np.where(ok, cosine, 0.0).sum(axis=2) / (length + 1.0)
        best = np.argmax(score, axis=1)
        agrees[obs] = ok[np.arange(len(tracks)), best]
    return agrees


def verify_by_reference_triangulation(
    query_rotation: FloatArray,
    query_translation: FloatArray,
    query_normalized: FloatArray,
    reference_index: IntArray,
    reference_rotations: FloatArray,
    reference_translations: FloatArray,
    reference_normalized: FloatArray,
    track_ids: IntArray,
    query_max_angle: float,
    reference_max_angles: FloatArray,
    min_views: int = 2,
    max_pair_views: int = 6,
    deadline: Deadline | None = None,
) -> StructureCheck:
    """Verify a query pose by triangulating tracks from the references alone.

    Args:
        query_rotation: (3, 3) query ``cam_from_world`` rotation.
        query_translation: (3,) query ``cam_from_world`` translation.
        query_normalized: (K, 2) normalised (undistorted, ``K⁻¹``-applied) query coordinates of
            the K inlier correspondences.
        reference_index: (K,) int64 index into the N references of each correspondence.
        reference_rotations: (N, 3, 3) reference ``cam_from_world`` rotations.
        reference_translations: (N, 3) reference ``cam_from_world`` translations.
        reference_normalized: (K, 2) normalised reference coordinates.
        track_ids: (K,) int64; correspondences through the same query keypoint share an id.
        query_max_angle: largest accepted angle (radians) between the query ray and the
            direction to the point (e.g. pixel threshold / focal length).
        reference_max_angles: (N,) the same for each reference.
        min_views: agreeing reference observations a point needs (>= 2).
        max_pair_views: two-view hypotheses come from pairs of a track's first this many
            observations (bounds the work on long tracks).
        deadline: checked between the steps (each well under 0.1 s on 100k correspondences).
    Returns:
        A ``StructureCheck``.

    Raises:
        DeadlinePassedError: ``deadline`` passed.
    """
    if min_views < 2:
        raise ValueError("a point needs at least two reference views to be triangulated")
    k = int(reference_index.shape[0])
    if k == 0:
        return StructureCheck(np.zeros(0, bool), np.zeros((0, 3)), np.zeros(0, bool), 0)
    _, inverse = np.unique(track_ids, return_inverse=True)
    tid = inverse.reshape(-1).astype(np.int64)
    num_tracks = int(tid.max()) + 1

    # reference rays and centres in world coordinates: d = Rᵀ r, C = −Rᵀ t
    rotations = reference_rotations[reference_index]  # (K, 3, 3)
    ray = np.einsum("kji,kj->ki", rotations, _unit_rays(reference_normalized))
    center = -np.einsum("kji,kj->ki", rotations, reference_translations[reference_index])
    cos_limit = np.cos(reference_max_angles[reference_index])  # (K,)
    num_candidates = int((np.bincount(tid) >= min_views).sum())

    _poll(deadline)
    use = _robust_agreement(
        tid, center, ray, cos_limit, min_views, max(max_pair_views, 2), deadline
    )
    _poll(deadline)
    # refine: midpoint of every agreeing ray, X = argmin Σ |(I − d dᵀ)(X − C)|²
    weight = use.astype(np.float64)
    projector = (np.eye(3) - ray[:, :, None] * ray[:, None, :]) * weight[:, None, None]
    normal = _group_sum(tid, projector, num_tracks)  # (T, 3, 3)
    rhs = _group_sum(tid, np.einsum("kij,kj->ki", projector, center), num_tracks)  # (T, 3)
    enough = np.bincount(tid, weights=weight, minlength=num_tracks) >= min_views
    points = np.full((num_tracks, 3), np.nan)
    solvable = np.flatnonzero(enough & _well_conditioned(normal))
    if solvable.size:
        points[solvable] = np.linalg.solve(normal[solvable], rhs[solvable][..., None])[..., 0]
    _poll(deadline)
    # NaN compares False; cos > cos(threshold) > 0 also means the point is in front
    use &= _cosine_to(points[tid], center, ray) > cos_limit
    enough = np.bincount(tid, weights=use.astype(np.float64), minlength=num_tracks) >= min_views

    # the query: the point must be in front of it and on its ray (one query ray per track)
    query_center = -query_rotation.T @ query_translation
    query_ray = _unit_rays(query_normalized) @ query_rotation  # Rᵀ r, (K, 3)
    first = np.unique(tid, return_index=True)[1]
    cos_query = _cosine_to(points, query_center, query_ray[first])  # (T,)
    point_verified = enough & (cos_query > np.cos(query_max_angle))
    return StructureCheck(
        correspondence_verified=use & point_verified[tid],
        points=points,
        point_verified=point_verified,
        num_tracks=num_candidates,
    )


def _normalized(camera: Camera, xy: FloatArray) -> FloatArray:
    """(M, 2) pixels → (M, 2) undistorted normalised coordinates (pycolmap's camera models)."""
    return normalized_from_pixels(camera, xy)


@dataclass(frozen=True)
class CheckedTracks:
    """A pose's inlier tracks checked in 3D (``check_structure``).

    Attributes:
        check: the ``StructureCheck``; its correspondences are the rows below.
        track_xy: (T, 2) the query pixel of each track (its ``check.points`` row).
        track_of: (K,) the track of each inlier correspondence.
        reference_of: (K,) the index into the references of each.
        inputs: the query camera, pose, references and inlier masks it was made of, and the
            threshold (``structure_of`` compares them by identity).
    """

    check: StructureCheck
    track_xy: FloatArray
    track_of: IntArray
    reference_of: IntArray
    inputs: tuple[Camera, Rigid3d, list[ReferenceObservation], list[BoolArray], float]

    def made_of(
        self,
        query_camera: Camera,
        cam_from_world: Rigid3d,
        references: list[ReferenceObservation],
        inliers: list[BoolArray],
        max_error_px: float,
    ) -> bool:
        """Whether it checked these very objects (not equal copies) at this threshold."""
        camera, pose, refs, masks, threshold = self.inputs
        return (
            camera is query_camera
            and pose is cam_from_world
            and refs is references
            and masks is inliers
            and threshold == max_error_px
        )


def check_structure(
    query_camera: Camera,
    cam_from_world: Rigid3d,
    references: list[ReferenceObservation],
    inliers: list[BoolArray],
    max_error_px: float,
    deadline: Deadline | None = None,
) -> CheckedTracks | None:
    """``verify_by_reference_triangulation`` of a pose's inlier tracks; None with inliers in
    fewer than two references.

    Query keypoints are identified across references by their exact pixel coordinates (every
    reference is matched against the same query keypoint array).

    Raises:
        DeadlinePassedError: ``deadline`` passed (checked between the steps).
    """
    used = [i for i, mask in enumerate(inliers) if mask.any()]
    if len(used) < 2:
        return None
    _poll(deadline)
    query_xy = np.concatenate([references[i].query_xy[inliers[i]] for i in used])
    track_xy, _, track_ids = unique_points(query_xy)
    _poll(deadline)
    reference_of = np.concatenate([np.full(int(inliers[i].sum()), i, np.int64) for i in used])
    check = verify_by_reference_triangulation(
        cam_from_world.rotation,
        cam_from_world.translation,
        _normalized(query_camera, query_xy),
        np.concatenate([np.full(int(inliers[i].sum()), j, np.int64) for j, i in enumerate(used)]),
        np.stack([references[i].cam_from_world.rotation for i in used]),
        np.stack([references[i].cam_from_world.translation for i in used]),
        np.concatenate(
            [
                _normalized(references[i].camera, references[i].reference_xy[inliers[i]])
                for i in used
            ]
        ),
        track_ids,
        max_error_px / float(np.mean(query_camera.focal_lengths)),
        np.array([max_error_px / float(np.mean(references[i].camera.focal_lengths)) for i in used]),
        deadline=deadline,
    )
    return CheckedTracks(
        check,
        track_xy,
        track_ids.astype(np.int64),
        reference_of,
        (query_camera, cam_from_world, references, inliers, max_error_px),
    )


def structure_of(
    result: EstimateResult,
    query_camera: Camera,
    references: list[ReferenceObservation],
    max_error_px: float,
    deadline: Deadline | None = None,
) -> CheckedTracks | None:
    """``check_structure`` of ``result``'s pose and inliers: the check ``verify_pose`` kept
    (``result.structure``) when it was made of the same camera, pose, references, masks and
    threshold, else a new one. ``result`` must have a pose.

    Raises:
        DeadlinePassedError: ``deadline`` passed during a new check.
    """
    pose = result.cam_from_world
    assert pose is not None
    kept = result.structure
    if kept is not None and kept.made_of(
        query_camera, pose, references, result.inliers, max_error_px
    ):
        return kept
    return check_structure(query_camera, pose, references, result.inliers, max_error_px, deadline)


def count_verified_points(
    query_camera: Camera,
    cam_from_world: Rigid3d,
    references: list[ReferenceObservation],
    inliers: list[BoolArray],
    max_error_px: float,
    deadline: Deadline | None = None,
) -> tuple[int, int]:
    """(verified points, candidate tracks) of a pose; see ``check_structure``."""
    return _counts(
        check_structure(query_camera, cam_from_world, references, inliers, max_error_px, deadline)
    )


def _counts(checked: CheckedTracks | None) -> tuple[int, int]:
    """(verified points, candidate tracks) of a check; (0, 0) for none."""
    if checked is None:
        return 0, 0
    return checked.check.num_verified_points, checked.check.num_tracks


def verify_pose(
    result: EstimateResult,
    query_camera: Camera,
    references: list[ReferenceObservation],
    options: EstimatorOptions,
    deadline: Deadline | None = None,
) -> EstimateResult:
    """Turn an estimator's pose into a ``no_consensus`` failure unless at least
    ``options.verification.min_verified_points`` of its inlier tracks verify in 3D, into a
    ``time_budget_exceeded`` one when ``deadline`` passes during the check (on 100k inliers
    it takes ~0.2 s, more on a loaded machine; checked between its steps).

    Applied by the pipeline to every estimator's answer. Results without a pose, without
    inliers (``pose_approx`` uses no correspondences) or with the check disabled
    (``min_verified_points = 0``) pass through unchanged. A singular system on the way is a
    ``degenerate_geometry`` failure. A pose that passes keeps its check as ``structure``.
    """
    if (
        result.cam_from_world is None
        or options.verification.min_verified_points <= 0
        or result.num_inliers == 0
    ):
        return result
    try:
        checked = check_structure(
            query_camera,
            result.cam_from_world,
            references,
            result.inliers,
            options.ransac.max_error_px,
            deadline,
        )
    except DeadlinePassedError:
        return replace(
            result,
            cam_from_world=None,
            confidence=0.0,
            failure_reason=FailureReason.TIME_BUDGET_EXCEEDED,
        )
    except np.linalg.LinAlgError:  # a system the conditioning checks let through
        logger.warning("pose verification met a singular system", exc_info=True)
        return replace(
            result,
            cam_from_world=None,
            confidence=0.0,
            failure_reason=FailureReason.DEGENERATE_GEOMETRY,
        )
    verified, tracks = _counts(checked)
    stats = {
        **result.stats,
        VERIFIED_POINTS: float(verified),
        "multi_reference_tracks": float(tracks),
    }
    if verified < options.verification.min_verified_points:
        return replace(
            result,
            cam_from_world=None,
            confidence=0.0,
            stats=stats,
            failure_reason=FailureReason.NO_CONSENSUS,
        )
    return replace(result, stats=stats, structure=checked)
