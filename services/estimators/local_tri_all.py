"""Local triangulation over all references ("SfM on the fly", the most accurate family in
Panek et al. 2025, "A Guide to Structureless Visual Localization"): tracks through each query
keypoint, RANSAC triangulation of every track over all retrieved references (threshold
``TriangulationOptions.max_error_px``: 2 px sparse, 8 px dense), then P3P LO-RANSAC with
refinement (PoseLib) on the query keypoints ↔ triangulated points.

The returned inlier masks are the matches within ``max_error_px`` Sampson error of the final
pose (the same definition as every other estimator); ``stats`` also reports the 2D–3D
inliers, and its ``score`` is their count.
"""

from __future__ import annotations

from services.estimators.base import FailureReason
from services.estimators.estimator import Estimator, Request, Solution
from services.estimators.tracks import build_tracks, pose_from_tracks, triangulate_tracks


class LocalTriAllEstimator(Estimator):
    name = "local_tri_all"
    min_matches = 1

    def solve(self, request: Request) -> Solution:
        stacked, options, stats = request.stacked, request.options, request.stats
        all_tracks = build_tracks(stacked, options.triangulation.track_merge_px)
        tracks = all_tracks.multi_view()
        stats["tracks"] = float(all_tracks.size)
        stats["tracks_multi_view"] = float(tracks.size)
        if tracks.size < 4:
            request.fail(FailureReason.TOO_FEW_MATCHES)
        tri = triangulate_tracks(
            stacked, tracks, options.triangulation.max_error_px, deadline=request.deadline
        )
        request.fail_if_expired()
        stats["points_triangulated"] = float(tri.valid.sum())
        if tri.valid.sum() < 4:
            request.fail(
                FailureReason.DEGENERATE_GEOMETRY
                if tracks.size >= 20
                else FailureReason.TOO_FEW_MATCHES
            )
        found = pose_from_tracks(
            stacked, tracks, tri, request.query_camera, options, request.deadline
        )
        if found is None:
            request.fail(FailureReason.NO_CONSENSUS)
        stats["iterations"] = float(found.iterations)
        stats["points_inliers"] = float(found.inliers.sum())
        stats["score"] = float(found.inliers.sum())
        if found.inliers.sum() < 4:
            request.fail(FailureReason.NO_CONSENSUS)
        return Solution(found.pose)
