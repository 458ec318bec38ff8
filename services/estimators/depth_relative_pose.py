"""Relative pose of one query–reference pair from the 3-point-with-depth solver in LO-RANSAC.

Hypotheses come in batches from ``geometry.depth_pose.relative_pose_3pt_depth`` (Umeyama on
three back-projected points per image), are scored by truncated (MSAC) Sampson error on a
random subset of the matches (preemptive scoring bounds the cost), and the best of each batch
is scored on all matches. Local optimisation re-fits the similarity on all inliers that have
depth. ``polish_relative_pose`` then runs PoseLib's Sampson refinement on adaptive inlier
sets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.estimators.correspondences import Deadline
from services.estimators.poselib_bridge import refine_relative_pose
from services.estimators.robust_scale import adaptive_threshold_px
from services.geometry.camera import Camera
from services.geometry.depth_pose import (
    back_project,
    relative_pose_3pt_depth,
    sampson_errors,
    similarity_from_points,
)
from services.geometry.rigid import Rigid3d
from services.types import BoolArray, FloatArray

BATCH = 200
SCORING_SUBSET = 256


@dataclass(frozen=True)
class DepthRelativePose:
    """``dst_from_src`` rotation, unit translation direction, scale of the similarity (metric
    translation = ``t * scale_t``), inlier mask over all matches, and iterations run."""

    R: FloatArray
    t: FloatArray
    translation_norm: float
    inliers: BoolArray
    iterations: int


def required_iterations(inlier_ratio: float, sample_size: int, success_prob: float = 0.9999) -> int:
    """Iterations after which an all-inlier sample was drawn with ``success_prob``."""
    p_good = inlier_ratio**sample_size
    if p_good >= 1.0 - 1e-12:
        return 1
    if p_good <= 1e-12:
        return 2**31
    return int(np.ceil(np.log(1.0 - success_prob) / np.log(1.0 - p_good)))


def _msac(errors: FloatArray, threshold: float) -> FloatArray:
    return np.asarray((np.minimum(errors, threshold) ** 2).sum(axis=-1), dtype=np.float64)


def ransac_relative_pose_depth(
    x_src: FloatArray,
    d_src: FloatArray,
    x_dst: FloatArray,
    d_dst: FloatArray,
    threshold: float,
    rng: np.random.Generator,
    min_iterations: int,
    max_iterations: int,
    deadline: Deadline,
    with_scale: bool = True,
) -> DepthRelativePose | None:
    """LO-RANSAC over the 3-point-with-depth solver.

    Args:
        x_src, x_dst: (M, 2) normalised correspondences; d_src, d_dst: (M,) depths (0 = none).
        threshold: Sampson inlier threshold in normalised units (pixels / focal).
        with_scale: depths known up to one scale per image (similarity) or metric (rigid).
    Returns:
        The best model, or None when fewer than 3 matches have both depths.
    """
    m = x_src.shape[0]
    with_depth = np.flatnonzero((d_src > 0) & (d_dst > 0))
    if with_depth.size < 3 or m < 5:
        return None
    subset = np.arange(m) if m <= SCORING_SUBSET else rng.choice(m, SCORING_SUBSET, replace=False)
    P_src = back_project(x_src, d_src)
    P_dst = back_project(x_dst, d_dst)
    best_score = np.inf
    best: tuple[FloatArray, FloatArray, FloatArray] | None = None
    iterations = 0
    needed = min_iterations
    while iterations < min(max(needed, min_iterations), max_iterations):
        if iterations > 0 and deadline.expired():
            break
        sample = with_depth[rng.integers(0, with_depth.size, size=(BATCH, 3))]
        iterations += BATCH
        distinct = (
            (sample[:, 0] != sample[:, 1])
            & (sample[:, 0] != sample[:, 2])
            & (sample[:, 1] != sample[:, 2])
        )
        sample = sample[distinct]
        tri = P_src[sample]
        area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        sample = sample[area > 1e-9]
        if sample.shape[0] == 0:
            continue
        R, t, _ = relative_pose_3pt_depth(
            x_src[sample], d_src[sample], x_dst[sample], d_dst[sample], with_scale
        )
        scores = _msac(sampson_errors(R, t, x_src[subset], x_dst[subset]), threshold)
        k = int(np.argmin(scores))
        full = _msac(sampson_errors(R[k : k + 1], t[k : k + 1], x_src, x_dst), threshold)[0]
        if full < best_score:
            best_score, best = _local_optimisation(
                R[k], t[k], P_src, P_dst, x_src, x_dst, d_src, d_dst, threshold, with_scale
            )
            inlier_ratio = float(
                (sampson_errors(best[0][None], best[1][None], x_src, x_dst)[0] < threshold).mean()
            )
            needed = required_iterations(inlier_ratio, 3)
    if best is None:
        return None
    R_best, t_best, _ = best
    errors = sampson_errors(R_best[None], t_best[None], x_src, x_dst)[0]
    norm = float(np.linalg.norm(t_best))
    direction = t_best / norm if norm > 0 else t_best
    return DepthRelativePose(R_best, direction, norm, errors < threshold, iterations)


def _local_optimisation(
    R: FloatArray,
    t: FloatArray,
    P_src: FloatArray,
    P_dst: FloatArray,
    x_src: FloatArray,
    x_dst: FloatArray,
    d_src: FloatArray,
    d_dst: FloatArray,
    threshold: float,
    with_scale: bool,
) -> tuple[float, tuple[FloatArray, FloatArray, FloatArray]]:
    """Re-fit the similarity on all inliers with depth while the MSAC score improves."""
    score = float(_msac(sampson_errors(R[None], t[None], x_src, x_dst), threshold)[0])
    model = (R, t, np.ones(1))
    for _ in range(3):
        inl = sampson_errors(model[0][None], model[1][None], x_src, x_dst)[0] < threshold
        inl &= (d_src > 0) & (d_dst > 0)
        if inl.sum() < 3:
            break
        R2, t2, s2 = similarity_from_points(P_src[inl][None], P_dst[inl][None], with_scale)
        new = float(_msac(sampson_errors(R2, t2, x_src, x_dst), threshold)[0])
        if new >= score:
            break
        score, model = new, (R2[0], t2[0], s2)
    return score, model


def polish_relative_pose(
    model: DepthRelativePose,
    ref_xy: FloatArray,
    query_xy: FloatArray,
    x_ref: FloatArray,
    x_query: FloatArray,
    ref_camera: Camera,
    query_camera: Camera,
    threshold: float,
    focal: float,
    rounds: int = 3,
) -> tuple[Rigid3d, BoolArray]:
    """PoseLib Sampson refinement of a ``query_from_ref`` model, ``rounds`` times, each on the
    matches within an adaptive threshold (≤ ``threshold``, normalised units). Returns the pose
    (unit translation) and its inliers at ``threshold``."""
    pose = Rigid3d(model.R, model.t)
    errors = sampson_errors(model.R[None], model.t[None], x_ref, x_query)[0] * focal
    for _ in range(rounds):
        thr_px = adaptive_threshold_px(errors, threshold * focal)
        keep = errors < thr_px
        refined = refine_relative_pose(
            ref_xy[keep], query_xy[keep], pose, ref_camera, query_camera, thr_px / 4.0
        )
        new_errors = (
            sampson_errors(refined.rotation[None], refined.translation[None], x_ref, x_query)[0]
            * focal
        )
        if (new_errors < threshold * focal).sum() < 0.95 * (errors < threshold * focal).sum():
            break
        pose, errors = refined, new_errors
    return pose, errors < threshold * focal
