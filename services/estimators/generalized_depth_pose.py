"""The query's ``cam_from_world`` from matches with depth over all references at once
(semi-generalized relative pose with depth), in LO-RANSAC; the method of ``e3p1``.

Minimal sample and hypothesis (one full query pose per sample):

* metric depths (the map's depths are metric and so is a depth-camera query): three matches
  with both depths, from any references, are back-projected — in the world frame from the
  posed references, in the query frame from the query depth — and a rigid alignment gives the
  query pose directly, metric (``solvers.absolute_pose_3pt_depth``).
* depths known up to one scale per image (e.g. monocular): three matches with depth in one
  reference A and one match of a second reference B (``solvers.absolute_pose_3pt_depth_plus_one``).

Hypotheses run through ``ransac.lo_ransac`` scored by truncated Sampson error (pixels) on a
random subset of all matches, the best of each batch on all matches; local optimisation is
PoseLib's generalized relative pose refinement (Sampson, all pairs) on the inliers
(``pose_triangulation.local_optimisation``).
"""

from __future__ import annotations

import numpy as np

from services.estimators.base import FailureReason
from services.estimators.correspondences import pose_sampson_errors_px
from services.estimators.estimator import Request
from services.estimators.pose_triangulation import local_optimisation
from services.estimators.ransac import RansacResult, lo_ransac
from services.estimators.solvers import (
    absolute_pose_3pt_depth,
    absolute_pose_3pt_depth_plus_one,
)
from services.geometry.depth_pose import back_project
from services.geometry.rigid import Rigid3d
from services.types import FloatArray, IntArray

# B query poses: rotations (B, 3, 3) and centres (B, 3)
Poses = tuple[FloatArray, FloatArray]


class _QueryPoseDepthProblem:
    batch_size = 128
    scoring_subset = 1000

    def __init__(
        self, request: Request, with_depth: IntArray, depth_weights: FloatArray, metric: bool
    ) -> None:
        self.request = request
        self.stacked = request.stacked
        self.with_depth = with_depth
        self.depth_weights = depth_weights
        self.metric = metric
        self.sample_size = 3 if metric else 4
        self.num_data = self.stacked.size

    def _metric(self, rng: np.random.Generator) -> Poses:
        stacked = self.stacked
        sample = self.with_depth[rng.integers(0, self.with_depth.size, size=(self.batch_size, 3))]
        points_world = (
            stacked.C_ref[stacked.ref_index[sample]]
            + stacked.ref_depth[sample][..., None] * stacked.ref_bearing_world[sample]
        )
        points_query = back_project(stacked.query_norm[sample], stacked.query_depth[sample])
        return absolute_pose_3pt_depth(points_world, points_query)

    def _up_to_scale(self, rng: np.random.Generator) -> Poses:
        stacked, with_depth, batch = self.stacked, self.with_depth, self.batch_size
        num_refs = stacked.offsets.shape[0] - 1
        ref_a = rng.choice(num_refs, size=batch, p=self.depth_weights)
        # three depth matches of reference A: draw among A's depth matches by rank
        starts = np.searchsorted(stacked.ref_index[with_depth], ref_a, side="left")
        ends = np.searchsorted(stacked.ref_index[with_depth], ref_a, side="right")
        pick = starts[:, None] + (rng.random((batch, 3)) * (ends - starts)[:, None]).astype(
            np.int64
        )
        sample = with_depth[np.minimum(pick, with_depth.size - 1)]
        # the +1 match: any match of another reference
        other = rng.integers(0, stacked.size, size=batch)
        R_q, C_q, ok = absolute_pose_3pt_depth_plus_one(
            back_project(stacked.ref_norm[sample], stacked.ref_depth[sample]),
            back_project(stacked.query_norm[sample], stacked.query_depth[sample]),
            stacked.R_ref[ref_a],
            stacked.C_ref[ref_a],
            stacked.query_norm[other],
            stacked.ref_bearing_world[other],
            stacked.C_ref[stacked.ref_index[other]],
        )
        ok &= stacked.ref_index[other] != ref_a
        return R_q[ok], C_q[ok]

    def hypotheses(self, rng: np.random.Generator) -> Poses | None:
        R_q, C_q = self._metric(rng) if self.metric else self._up_to_scale(rng)
        return (R_q, C_q) if R_q.shape[0] > 0 else None

    def batch_errors(self, batch: Poses, subset: IntArray) -> FloatArray:
        return pose_sampson_errors_px(self.stacked, batch[0], batch[1], subset)

    def select(self, batch: Poses, k: int) -> Rigid3d:
        R, C = batch[0][k], batch[1][k]
        return Rigid3d(R, -R @ C)

    def errors(self, model: Rigid3d) -> FloatArray:
        errors: FloatArray = pose_sampson_errors_px(
            self.stacked, model.rotation[None], model.center[None], deadline=self.request.deadline
        )[0]
        return errors

    def local_optimisation(self, model: Rigid3d, errors: FloatArray) -> tuple[Rigid3d, FloatArray]:
        request = self.request
        return local_optimisation(
            model,
            self.stacked,
            request.references,
            request.query_camera,
            request.options,
            request.deadline,
            errors=errors,
        )


def ransac_query_pose_depth(request: Request) -> RansacResult[Rigid3d]:
    """LO-RANSAC over the matches of all references; fails the request with too few matches
    with depth for the sample."""
    stacked = request.stacked
    with_depth = np.flatnonzero((stacked.query_depth > 0) & (stacked.ref_depth > 0))
    if with_depth.size < 3:
        request.fail(FailureReason.TOO_FEW_MATCHES)
    metric = request.options.e3p1.metric_depth
    counts = np.bincount(stacked.ref_index[with_depth], minlength=len(request.references))
    if not metric and (counts >= 3).sum() < 1:
        request.fail(FailureReason.TOO_FEW_MATCHES)
    depth_weights = np.where(counts >= 3, counts, 0).astype(np.float64)
    depth_weights /= max(depth_weights.sum(), 1.0)
    problem = _QueryPoseDepthProblem(request, with_depth, depth_weights, metric)
    options = request.options.ransac
    rng = np.random.default_rng(options.seed)
    return lo_ransac(problem, options.max_error_px, options, rng, request.deadline)
