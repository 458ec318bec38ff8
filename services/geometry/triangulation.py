"""Batched point triangulation from posed views, including RANSAC over each track's views.

All inputs are normalised image coordinates (see ``projection.normalized_from_pixels``) and
``cam_from_world`` projection matrices ``[R | t]``; errors are converted to approximate pixels
with a per-view focal length. Every function works on whole batches of tracks: no Python loop
runs per point.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from services.geometry.pose_covariance import inverse_3x3
from services.types import BoolArray, FloatArray


def triangulate_dlt(
    normalized: FloatArray, projections: FloatArray, weights: FloatArray
) -> FloatArray:
    """Linear (DLT) triangulation of many tracks at once.

    Args:
        normalized: (T, V, 2) normalised observations of T tracks in V views.
        projections: (V, 3, 4) ``cam_from_world`` matrices ``[R | t]`` of the views, or
            (T, V, 3, 4) per track.
        weights: (T, V) weight of each observation; 0 drops it (a track needs two views > 0).
    Returns:
        (T, 3) world points (NaN-free; meaningless where fewer than two views have weight).

    Kept rather than pycolmap's ``triangulate_point`` / ``triangulate_multi_view_point``,
    which take one point per call: the same points to 1e-13 on exact data, and over 2000
    points (one thread, median of 5) this took 4.5 ms for two views where a loop of
    ``triangulate_point`` took 9.1 ms (2.0×), 5.3 ms for five views against 9.0 ms (1.7×),
    and 4.2 ms for five views with a 0/1 weight per observation (the inlier refinement)
    against 16.2 ms for the loop picking each point's views (3.9×). Real-valued weights and
    per-track projections have no pycolmap counterpart.
    """
    P = np.broadcast_to(projections, (*normalized.shape[:2], 3, 4))
    rows_x = normalized[..., 0:1] * P[..., 2, :] - P[..., 0, :]  # (T, V, 4)
    rows_y = normalized[..., 1:2] * P[..., 2, :] - P[..., 1, :]
    A = (
        np.concatenate([rows_x, rows_y], axis=1)
        * np.concatenate([weights, weights], axis=1)[..., None]
    )
    # the null vector of A is the eigenvector of AᵀA with the smallest eigenvalue; a track
    # with a non-finite observation is dropped like one without views (eigh would not converge)
    AtA = np.swapaxes(A, 1, 2) @ A
    _, vecs = np.linalg.eigh(np.where(np.isfinite(AtA).all(axis=(1, 2))[:, None, None], AtA, 0.0))
    X = vecs[..., :, 0]
    w = X[:, 3]
    w = np.where(np.abs(w) < 1e-12, 1e-12, w)
    return np.asarray(X[:, :3] / w[:, None], dtype=np.float64)


def triangulate_pairs(normalized: FloatArray, projections: FloatArray) -> FloatArray:
    """Two-view linear triangulation of many tracks at once, with the point's fourth
    coordinate fixed at 1: the least-squares solution of the DLT rows as a 3 × 3 system
    (normal equations, inverted by their adjugate). It differs from ``triangulate_dlt``'s null
    vector only by how the residual is weighed, and takes a third of its time (numpy's batched
    ``eigh`` is the cost there): ``ransac_triangulate`` makes its hypotheses with it.

    Args:
        normalized: (N, 2, 2) normalised observations of N tracks in their two views.
        projections: (N, 2, 3, 4) ``cam_from_world`` of each track's two views.
    Returns:
        (N, 3) world points; NaN where the two rays are parallel.
    """
    rows_x = normalized[..., 0:1] * projections[..., 2, :] - projections[..., 0, :]
    rows_y = normalized[..., 1:2] * projections[..., 2, :] - projections[..., 1, :]
    A = np.concatenate([rows_x, rows_y], axis=1)  # (N, 4, 4)
    inverse, solvable = inverse_3x3(np.swapaxes(A[..., :3], 1, 2) @ A[..., :3])
    points = -np.einsum("nij,nj->ni", inverse, np.einsum("nkj,nk->nj", A[..., :3], A[..., 3]))
    points[~solvable] = np.nan
    return np.asarray(points, dtype=np.float64)


def reprojection_errors(
    points: FloatArray, normalized: FloatArray, projections: FloatArray, focals: FloatArray
) -> tuple[FloatArray, BoolArray]:
    """Reprojection error of points in views, in approximate pixels.

    Args:
        points: (T, 3) world points.
        normalized: (T, V, 2) observations.
        projections: (V, 3, 4) ``cam_from_world``.
        focals: (V,) focal lengths in pixels.
    Returns:
        (T, V) errors (inf behind the camera) and (T, V) depth > 0 mask.
    """
    X_cam = np.einsum("vij,tj->tvi", projections[:, :, :3], points) + projections[:, :, 3]
    z = X_cam[..., 2]
    in_front = z > 1e-9
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = X_cam[..., :2] / z[..., None]
    err = np.linalg.norm(proj - normalized, axis=-1) * focals
    return np.where(in_front, err, np.inf), in_front


# the (T, V, V) ray-angle tables are built this many entries at a time (V = 100 views: 200
# tracks, ~16 MB and a few milliseconds a chunk; in one piece 20k tracks took 1.6 GB and 6 s)
ANGLE_CHUNK_ENTRIES = 2_000_000
# ``ransac_triangulate`` checks its hypotheses in every view at most this many (hypothesis,
# view) entries at a time (~25 MB of temporaries), one view pair's at least
HYPOTHESIS_CHUNK_ENTRIES = 250_000


def max_ray_angle_deg(
    points: FloatArray,
    centers: FloatArray,
    mask: BoolArray,
    stop: Callable[[], bool] | None = None,
) -> FloatArray | None:
    """Largest angle between the rays from the masked views' centres to each point.

    Args:
        points: (T, 3); centers: (V, 3); mask: (T, V).
        stop: polled between chunks of tracks; None is returned once it answers True.
    Returns:
        (T,) degrees (0 where fewer than two views are masked).
    """
    num_views = centers.shape[0]
    chunk = max(1, ANGLE_CHUNK_ENTRIES // max(num_views * num_views, 1))
    min_cos = np.ones(points.shape[0])
    for start in range(0, points.shape[0], chunk):
        if stop is not None and stop():
            return None
        rows = slice(start, start + chunk)
        rays = points[rows, None, :] - centers[None, :, :]
        rays /= np.maximum(np.linalg.norm(rays, axis=-1, keepdims=True), 1e-12)
        cos = np.einsum("tai,tbi->tab", rays, rays)
        both = mask[rows, :, None] & mask[rows, None, :]
        min_cos[rows] = np.where(both, cos, 1.0).min(axis=(1, 2))
    return np.asarray(np.degrees(np.arccos(np.clip(min_cos, -1.0, 1.0))), dtype=np.float64)


@dataclass(frozen=True)
class TriangulatedTracks:
    """Result of ``ransac_triangulate``.

    Attributes:
        points: (T, 3) world points.
        inliers: (T, V) views that agree with the point within the threshold.
        valid: (T,) tracks with at least two inlier views, enough parallax, positive depth.
    """

    points: FloatArray
    inliers: BoolArray
    valid: BoolArray


def ransac_triangulate(
    normalized: FloatArray,
    observed: BoolArray,
    projections: FloatArray,
    focals: FloatArray,
    centers: FloatArray,
    threshold_px: float,
    min_angle_deg: float = 1.0,
    stop: Callable[[], bool] | None = None,
) -> TriangulatedTracks:
    """Robust triangulation of every track: each pair of observing views proposes a point
    (``triangulate_pairs``), the point with most views within ``threshold_px`` wins (the
    first such pair), and a DLT over its inlier views refines it. With V ≤ 10 views this is
    exhaustive (≤ 45 hypotheses per track).

    Args:
        normalized: (T, V, 2) normalised observations (anything where not observed).
        observed: (T, V) which views observe each track.
        projections: (V, 3, 4) ``cam_from_world`` of the views.
        focals: (V,) focal lengths in pixels (error units).
        centers: (V, 3) view centres, for the parallax check.
        threshold_px: inlier threshold on the reprojection error.
        min_angle_deg: least triangulation angle of a valid point.
        stop: polled between chunks of view pairs and between the later steps' chunks (a
            request's deadline: with V = 100 views there are 4950 pairs, seconds of work);
            once it answers True no track is valid.
    Returns:
        ``TriangulatedTracks``.
    """
    T, V = observed.shape
    normalized = np.where(observed[..., None], normalized, 0.0)
    all_pairs = np.stack(np.triu_indices(V, k=1), axis=1)
    best_count = np.zeros(T, dtype=np.int64)
    best_points = np.zeros((T, 3))
    stopped = TriangulatedTracks(best_points, np.zeros((T, V), bool), np.zeros(T, bool))
    # the pairs' hypotheses are made a chunk of pairs at a time, vectorised over tracks and
    # pairs; the winner is the first hypothesis in pair order with the most inlier views
    per_chunk = max(1, HYPOTHESIS_CHUNK_ENTRIES // max(T * V, 1))
    for start in range(0, all_pairs.shape[0], per_chunk):
        if stop is not None and stop():
            return stopped
        pairs = all_pairs[start : start + per_chunk]
        both = observed[:, pairs[:, 0]] & observed[:, pairs[:, 1]]  # (T, P)
        pair_of, track_of = np.nonzero(both.T)  # pair-major: ties go to the earlier pair
        if track_of.size == 0:
            continue
        views = pairs[pair_of]  # (N, 2)
        pts = triangulate_pairs(normalized[track_of[:, None], views], projections[views])
        err, _ = reprojection_errors(pts, normalized[track_of], projections, focals)
        count = ((err < threshold_px) & observed[track_of]).sum(axis=1)
        order = np.lexsort((np.arange(track_of.size), -count, track_of))
        first = np.ones(order.size, bool)
        first[1:] = track_of[order[1:]] != track_of[order[:-1]]
        winner = order[first]
        tracks = track_of[winner]
        better = count[winner] > best_count[tracks]
        best_count[tracks[better]] = count[winner][better]
        best_points[tracks[better]] = pts[winner][better]
    err, _ = reprojection_errors(best_points, normalized, projections, focals)
    inliers = (err < threshold_px) & observed
    refined = triangulate_dlt(normalized, projections, inliers.astype(np.float64))
    enough = inliers.sum(axis=1) >= 2
    best_points = np.where(enough[:, None], refined, best_points)
    err, _ = reprojection_errors(best_points, normalized, projections, focals)
    inliers = (err < threshold_px) & observed
    angle = max_ray_angle_deg(best_points, centers, inliers, stop)
    if angle is None:
        return stopped
    valid = (inliers.sum(axis=1) >= 2) & (angle >= min_angle_deg)
    valid &= np.all(np.isfinite(best_points), axis=1)
    return TriangulatedTracks(best_points, inliers & valid[:, None], valid)
