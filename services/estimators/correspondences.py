"""All query–reference matches of a request stacked into flat arrays, their Sampson errors under
a query pose, and random subsets of them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.estimators.base import (
    ReferenceObservation,
)
from services.estimators.ransac import Deadline
from services.geometry.camera import Camera
from services.geometry.projection import mean_focal, normalized_from_pixels
from services.types import BoolArray, FloatArray, IntArray


@dataclass(frozen=True)
class StackedMatches:
    """The matches of all references, concatenated (N matches in all, V references).

    Attributes:
        ref_index: (N,) index into the request's reference list of each match.
        offsets: (V + 1,) match ``ref_index == i`` occupy ``offsets[i]:offsets[i + 1]``.
        query_norm, ref_norm: (N, 2) normalised (undistorted) coordinates.
        query_depth, ref_depth: (N,) depths, 0 where unknown.
        ref_bearing_world: (N, 3) ``R_refᵀ·(x, y, 1)``: the reference ray in world axes.
        R_ref: (V, 3, 3) reference rotations; C_ref: (V, 3) reference centres.
        focal: (N,) mean of the query's and the reference's focal lengths, in pixels.
        ref_focal: (N,) the reference's focal length, in pixels.
        query_xy: (N, 2) query pixels (COLMAP convention).
    """

    ref_index: IntArray
    offsets: IntArray
    query_norm: FloatArray
    ref_norm: FloatArray
    query_depth: FloatArray
    ref_depth: FloatArray
    ref_bearing_world: FloatArray
    R_ref: FloatArray
    C_ref: FloatArray
    focal: FloatArray
    ref_focal: FloatArray
    query_xy: FloatArray

    @property
    def size(self) -> int:
        return int(self.ref_index.shape[0])

    def split(self, flat: BoolArray) -> list[BoolArray]:
        """Per-reference masks from an (N,) mask over the stacked matches."""
        return [
            flat[self.offsets[i] : self.offsets[i + 1]].copy()
            for i in range(self.offsets.shape[0] - 1)
        ]


def _depth_or_zeros(depth: FloatArray | None, count: int) -> FloatArray:
    if depth is None:
        return np.zeros(count)
    d = np.asarray(depth, dtype=np.float64).reshape(-1)
    return np.where(np.isfinite(d) & (d > 0), d, 0.0)


def stack_matches(query_camera: Camera, references: list[ReferenceObservation]) -> StackedMatches:
    counts = np.array([ref.num_matches for ref in references], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    ref_index = np.repeat(np.arange(len(references), dtype=np.int64), counts)
    R_ref = (
        np.stack([ref.cam_from_world.rotation for ref in references])
        if references
        else np.zeros((0, 3, 3))
    )
    C_ref = (
        np.stack([ref.cam_from_world.center for ref in references])
        if references
        else np.zeros((0, 3))
    )
    f_query = mean_focal(query_camera)

    def cat(parts: list[FloatArray], width: int) -> FloatArray:
        return np.concatenate(parts, axis=0) if parts else np.zeros((0, width))

    query_norm = cat([normalized_from_pixels(query_camera, ref.query_xy) for ref in references], 2)
    ref_norm = cat([normalized_from_pixels(ref.camera, ref.reference_xy) for ref in references], 2)
    query_depth = np.concatenate(
        [_depth_or_zeros(ref.query_depth, ref.num_matches) for ref in references] or [np.zeros(0)]
    )
    ref_depth = np.concatenate(
        [_depth_or_zeros(ref.reference_depth, ref.num_matches) for ref in references]
        or [np.zeros(0)]
    )
    focal = np.concatenate(
        [np.full(ref.num_matches, 0.5 * (f_query + mean_focal(ref.camera))) for ref in references]
        or [np.zeros(0)]
    )
    ref_focal = np.concatenate(
        [np.full(ref.num_matches, mean_focal(ref.camera)) for ref in references] or [np.zeros(0)]
    )
    query_xy = cat([np.asarray(ref.query_xy, dtype=np.float64) for ref in references], 2)
    h_ref = np.concatenate([ref_norm, np.ones((ref_norm.shape[0], 1))], axis=1)
    ref_bearing_world = np.einsum("nji,nj->ni", R_ref[ref_index], h_ref)
    return StackedMatches(
        ref_index, offsets, query_norm, ref_norm, query_depth, ref_depth,
        ref_bearing_world, R_ref, C_ref, focal, ref_focal, query_xy,
    )  # fmt: skip


# matches per chunk of a pass that polls a deadline (100k matches take ~0.05-0.2 s a pass)
SAMPSON_CHUNK = 8192


def pose_sampson_errors_px(
    stacked: StackedMatches,
    R_q: FloatArray,
    C_q: FloatArray,
    subset: IntArray | None = None,
    deadline: Deadline | None = None,
) -> FloatArray:
    """Sampson error (≈ pixels) of every match under query-pose hypotheses.

    The relative pose of the query to reference i follows from both absolute poses:
    ``R = R_q·R_iᵀ``, ``t = R_q·(C_i − C_q)``; everything is evaluated in world axes, batched.

    Args:
        R_q: (B, 3, 3) query rotations; C_q: (B, 3) query centres.
        subset: optional (S,) match indices to evaluate (errors come in sorted index order).
        deadline: when given, the matches are evaluated in chunks of ``SAMPSON_CHUNK`` and the
            deadline is checked before each (the errors are the same, element for element).
    Returns:
        (B, N) or (B, S) errors.

    Raises:
        DeadlinePassedError: ``deadline`` passed before the last chunk.
    """
    idx = np.arange(stacked.size) if subset is None else np.sort(subset)
    if deadline is None:
        return _sampson_errors_px(stacked, R_q, C_q, idx)
    parts = []
    for start in range(0, max(idx.shape[0], 1), SAMPSON_CHUNK):
        deadline.check()
        parts.append(_sampson_errors_px(stacked, R_q, C_q, idx[start : start + SAMPSON_CHUNK]))
    return np.concatenate(parts, axis=1)


def _sampson_errors_px(
    stacked: StackedMatches, R_q: FloatArray, C_q: FloatArray, idx: IntArray
) -> FloatArray:
    """``pose_sampson_errors_px`` of the matches ``idx`` (sorted)."""
    ref = stacked.ref_index[idx]
    b_r = stacked.ref_bearing_world[idx]
    h_q = np.concatenate([stacked.query_norm[idx], np.ones((idx.shape[0], 1))], axis=1)
    u = stacked.C_ref[ref][None, :, :] - C_q[:, None, :]  # (B, S, 3)
    cross = np.cross(u, b_r[None])
    a = h_q @ R_q  # (B, S, 3): R_qᵀ x̃_q
    num = (a * cross).sum(axis=-1)
    Ex1 = cross @ np.swapaxes(R_q, 1, 2)  # R_q (u × b_r)
    w = np.cross(a, u)
    Etx2 = np.empty_like(w)
    for i in np.unique(ref):  # loop over references (≤ top-k), vectorised over matches
        sel = ref == i
        Etx2[:, sel] = w[:, sel] @ stacked.R_ref[i].T  # R_i (a × u)
    den = Ex1[..., 0] ** 2 + Ex1[..., 1] ** 2 + Etx2[..., 0] ** 2 + Etx2[..., 1] ** 2
    err = np.abs(num) / np.sqrt(np.maximum(den, 1e-300))
    return np.asarray(err * stacked.focal[idx][None], dtype=np.float64)


def random_subset(num: int, cap: int, rng: np.random.Generator) -> IntArray:
    """Sorted indices of at most ``cap`` of ``num`` items, uniformly at random (all of them,
    in order, when ``num <= cap``)."""
    if num <= cap:
        return np.arange(num, dtype=np.int64)
    return np.sort(rng.choice(num, size=cap, replace=False)).astype(np.int64)


def unique_points(xy: FloatArray) -> tuple[FloatArray, IntArray, IntArray]:
    """The distinct (x, y) rows of ``xy`` in lexicographic order, the index of each one's
    first row, and each row's index among them: ``np.unique(xy, axis=0, return_index=True,
    return_inverse=True)``, about 8× faster on thousands of keypoints (the rows as complex
    numbers: a 1-D unique in the same order)."""
    rows = np.ascontiguousarray(xy, dtype=np.float64).view(np.complex128).reshape(-1)
    distinct, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
    points = np.stack([distinct.real, distinct.imag], axis=1)
    return points, first.astype(np.int64), inverse.reshape(-1).astype(np.int64)
