"""Local triangulation per reference pair ("SfM on the fly", pairs variant): for every pair of
references, the query keypoints matched in both are triangulated from the two references (2-view
DLT, ``TriangulationOptions.max_error_px`` check, ≥ 1° parallax), P3P LO-RANSAC (PoseLib) gives a
query pose from those points, and the pose with most 2D–3D inliers wins; it is then refined on the
points of all pairs that reproject within an adaptive threshold (a step beyond the best pair's
pose: it costs one refinement and steadies the accuracy).

Pairs are tried in decreasing order of shared tracks; when the time budget runs out the best
pose so far is kept (``stats["budget_exhausted"] = 1``), or ``time_budget_exceeded`` without
one. Inlier masks: matches within ``max_error_px`` Sampson error of the final pose.
"""

from __future__ import annotations

import itertools

import numpy as np

from services.estimators.base import FailureReason
from services.estimators.estimator import Estimator, Request, Solution
from services.estimators.tracks import (
    TrackPose,
    build_tracks,
    pose_from_tracks,
    refine_on_points,
    triangulate_tracks,
)
from services.types import FloatArray

MIN_SHARED_TRACKS = 6  # a pair sharing fewer query keypoints is not tried


class LocalTriPairsEstimator(Estimator):
    name = "local_tri_pairs"
    min_matches = 1

    def solve(self, request: Request) -> Solution:
        stacked, options, stats = request.stacked, request.options, request.stats
        tracks = build_tracks(stacked, options.triangulation.track_merge_px)
        observed = tracks.observed.astype(np.int64)
        shared = observed.T @ observed  # (V, V) tracks seen by both references
        pairs = [
            (a, b)
            for a, b in itertools.combinations(range(len(request.references)), 2)
            if shared[a, b] >= MIN_SHARED_TRACKS
        ]
        pairs.sort(key=lambda ab: -int(shared[ab[0], ab[1]]))
        stats["tracks"] = float(tracks.size)
        stats["pairs"] = float(len(pairs))
        if not pairs:
            request.fail(FailureReason.TOO_FEW_MATCHES)
        best: TrackPose | None = None
        best_pair = (-1, -1)
        iterations = 0
        tried = 0
        exhausted = False
        all_points: list[FloatArray] = []
        all_query_xy: list[FloatArray] = []
        for k, (a, b) in enumerate(pairs):
            if request.deadline.expired():
                exhausted = True
                break
            in_pair = tracks.observed[:, a] & tracks.observed[:, b]
            sub = tracks.subset(in_pair)
            views = np.array([a, b], dtype=np.int64)
            tri = triangulate_tracks(
                stacked, sub, options.triangulation.max_error_px, views, deadline=request.deadline
            )
            tried += 1
            if tri.valid.sum() < MIN_SHARED_TRACKS:
                continue
            all_points.append(tri.points[tri.valid])
            all_query_xy.append(stacked.query_xy[sub.query_match[tri.valid]])
            found = pose_from_tracks(
                stacked, sub, tri, request.query_camera, options, request.deadline, len(pairs) - k
            )
            if found is None:
                continue
            iterations += found.iterations
            if best is None or found.inliers.sum() > best.inliers.sum():
                best, best_pair = found, (a, b)
        stats["pairs_tried"] = float(tried)
        stats["iterations"] = float(iterations)
        stats["budget_exhausted"] = float(exhausted)
        if best is None:
            request.fail(
                FailureReason.TIME_BUDGET_EXCEEDED if exhausted else FailureReason.NO_CONSENSUS
            )
        stats["best_pair_a"], stats["best_pair_b"] = float(best_pair[0]), float(best_pair[1])
        stats["points_inliers"] = float(best.inliers.sum())
        stats["score"] = float(best.inliers.sum())
        # final refinement on the points of every pair that agree with the best pose
        pose, used = refine_on_points(
            best.pose,
            np.concatenate(all_points),
            np.concatenate(all_query_xy),
            request.query_camera,
            options,
            request.deadline,
        )
        stats["points_refined"] = float(used)
        return Solution(pose)
