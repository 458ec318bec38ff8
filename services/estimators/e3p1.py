"""E3+1: semi-generalized relative pose with depth (own LO-RANSAC over all pairs at once).

Minimal sample and hypothesis (one full query ``cam_from_world`` per sample):

* ``metric_depth=True`` (default; the map's depths are metric and so is a depth-camera query):
  three matches with both depths, from any references, are back-projected — in the world
  frame from the posed references, in the query frame from the query depth — and a rigid
  alignment (Umeyama, s = 1) gives the query pose directly, metric.
* ``metric_depth=False`` (depths known up to one scale per image, e.g. monocular): three
  matches with depth in one reference A give the similarity query ← A (rotation and the
  direction of the query centre from A), and one match of a second reference B fixes the scale
  along that direction by intersecting its query ray with B's ray (the "+1", as in E5+1).

Hypotheses are scored in batches by truncated Sampson error on a random subset of all matches
(preemptive), the best of each batch on all matches; local optimisation is PoseLib's
generalized relative pose refinement (Sampson, all pairs) on the inliers, re-run while the
score improves. Inlier masks: matches within ``max_error_px`` Sampson error.
"""

from __future__ import annotations

import numpy as np

from services.estimators.base import (
    EstimateResult,
    EstimatorOptions,
    FailureReason,
    ReferenceObservation,
)
from services.estimators.correspondences import (
    Deadline,
    StackedMatches,
    finish,
    pose_sampson_errors_px,
    precheck,
    stack_matches,
)
from services.estimators.depth_relative_pose import required_iterations
from services.estimators.pose_triangulation import local_optimisation
from services.geometry.camera import Camera
from services.geometry.depth_pose import back_project, similarity_from_points
from services.geometry.rigid import Rigid3d
from services.types import FloatArray, IntArray

BATCH = 128
SCORING_SUBSET = 1000


def _hypotheses_metric(
    stacked: StackedMatches, with_depth: IntArray, rng: np.random.Generator
) -> tuple[FloatArray, FloatArray]:
    """(B, 3, 3) rotations and (B, 3) centres from rigid 3-point alignments."""
    sample = with_depth[rng.integers(0, with_depth.size, size=(BATCH, 3))]
    X_world = (
        stacked.C_ref[stacked.ref_index[sample]]
        + stacked.ref_depth[sample][..., None] * stacked.ref_bearing_world[sample]
    )
    P_query = back_project(stacked.query_norm[sample], stacked.query_depth[sample])
    R, t, _ = similarity_from_points(X_world, P_query, with_scale=False)
    return R, -np.einsum("bji,bj->bi", R, t)


def _hypotheses_up_to_scale(
    stacked: StackedMatches,
    with_depth: IntArray,
    depth_weights: FloatArray,
    rng: np.random.Generator,
) -> tuple[FloatArray, FloatArray]:
    """(B, 3, 3) rotations and (B, 3) centres from 3 depth matches in one reference A plus one
    match in another reference B."""
    num_refs = stacked.offsets.shape[0] - 1
    ref_a = rng.choice(num_refs, size=BATCH, p=depth_weights)
    # three depth matches of reference A: draw among A's depth matches by rank
    starts = np.searchsorted(stacked.ref_index[with_depth], ref_a, side="left")
    ends = np.searchsorted(stacked.ref_index[with_depth], ref_a, side="right")
    pick = starts[:, None] + (rng.random((BATCH, 3)) * (ends - starts)[:, None]).astype(np.int64)
    sample = with_depth[np.minimum(pick, with_depth.size - 1)]
    # the +1 match: any match of another reference
    other = rng.integers(0, stacked.size, size=BATCH)
    P_ref = back_project(stacked.ref_norm[sample], stacked.ref_depth[sample])
    P_query = back_project(stacked.query_norm[sample], stacked.query_depth[sample])
    R_qa, t_qa, _ = similarity_from_points(P_ref, P_query, with_scale=True)
    R_a = stacked.R_ref[ref_a]
    R_q = R_qa @ R_a
    v = np.einsum("bji,bj->bi", R_q, t_qa)  # C_q = C_A − λ·R_qᵀ t_qa, λ > 0 (unit depth scale)
    a = np.einsum("bji,bj->bi", R_q, np.c_[stacked.query_norm[other], np.ones(BATCH)])
    n = np.cross(a, stacked.ref_bearing_world[other])
    C_a = stacked.C_ref[ref_a]
    C_b = stacked.C_ref[stacked.ref_index[other]]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = ((C_a - C_b) * n).sum(axis=1) / (v * n).sum(axis=1)
    ok = (stacked.ref_index[other] != ref_a) & np.isfinite(lam) & (lam > 0)
    C_q = C_a - lam[:, None] * v
    return R_q[ok], C_q[ok]


class E3p1Estimator:
    name = "e3p1"

    def estimate(
        self,
        query_camera: Camera,
        references: list[ReferenceObservation],
        options: EstimatorOptions,
    ) -> EstimateResult:
        deadline = Deadline(options.time_budget_s)
        # like E5+1: at least two references with 5 matches each
        reason = precheck(references, min_matches=5)
        if reason is not None:
            return EstimateResult.failure(reason, references)
        stacked = stack_matches(query_camera, references)
        with_depth = np.flatnonzero((stacked.query_depth > 0) & (stacked.ref_depth > 0))
        if with_depth.size < 3:
            return EstimateResult.failure(FailureReason.TOO_FEW_MATCHES, references)
        counts = np.bincount(stacked.ref_index[with_depth], minlength=len(references))
        if not options.metric_depth and (counts >= 3).sum() < 1:
            return EstimateResult.failure(FailureReason.TOO_FEW_MATCHES, references)
        depth_weights = np.where(counts >= 3, counts, 0).astype(np.float64)
        depth_weights /= max(depth_weights.sum(), 1.0)
        rng = np.random.default_rng(options.seed)
        thr = options.max_error_px
        subset = (
            np.arange(stacked.size)
            if stacked.size <= SCORING_SUBSET
            else rng.choice(stacked.size, SCORING_SUBSET, replace=False)
        )
        sample_size = 3 if options.metric_depth else 4
        best: Rigid3d | None = None
        best_score = np.inf
        iterations = 0
        needed = options.min_iterations
        while iterations < min(max(needed, options.min_iterations), options.max_iterations):
            if deadline.expired():
                break
            iterations += BATCH
            if options.metric_depth:
                R_q, C_q = _hypotheses_metric(stacked, with_depth, rng)
            else:
                R_q, C_q = _hypotheses_up_to_scale(stacked, with_depth, depth_weights, rng)
            if R_q.shape[0] == 0:
                continue
            errors = pose_sampson_errors_px(stacked, R_q, C_q, subset)
            k = int(np.argmin((np.minimum(errors, thr) ** 2).sum(axis=1)))
            full = pose_sampson_errors_px(stacked, R_q[k : k + 1], C_q[k : k + 1])[0]
            score = float((np.minimum(full, thr) ** 2).sum())
            if score < best_score:
                candidate = Rigid3d(R_q[k], -R_q[k] @ C_q[k])
                refined, inliers = local_optimisation(
                    candidate, stacked, references, query_camera, options, deadline
                )
                full = pose_sampson_errors_px(
                    stacked, refined.rotation[None], refined.center[None]
                )[0]
                best, best_score = refined, float((np.minimum(full, thr) ** 2).sum())
                needed = required_iterations(float((full < thr).mean()), sample_size)
        stats: dict[str, float] = {"iterations": float(iterations)}
        if best is None:
            reason = (
                FailureReason.TIME_BUDGET_EXCEEDED
                if deadline.expired()
                else FailureReason.NO_CONSENSUS
            )
            return EstimateResult.failure(reason, references, stats)
        errors = pose_sampson_errors_px(stacked, best.rotation[None], best.center[None])[0]
        inliers = errors < thr
        stats["score"] = float(inliers.sum())
        return finish(best, stacked.split(inliers), references, options, stats)
