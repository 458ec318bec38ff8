"""Local triangulation over all references ("SfM on the fly", the most accurate family in
Panek et al. 2025, "A Guide to Structureless Visual Localization"): tracks through each query
keypoint, RANSAC triangulation of every track over all retrieved references (threshold
``TriangulationOptions.max_error_px``: 2 px sparse, 8 px dense), then P3P LO-RANSAC with
refinement (PoseLib) on the query keypoints ↔ triangulated points, and a last refinement on the
points that fit that pose best (``refine_keeping_support``: an adaptive threshold, 3σ of the
reprojection errors, and a tight loss; kept unless fewer points then fit within
``max_error_px``). On kitti05 (forward motion, 1226 × 370 frames) the last refinement took the
median position error from 1.4 to 1.2 cm with ``sift`` and from 1.8 to 1.5 cm with
``xfeat-lg``; on redkitchen it left the recall and median as they were.

When that refinement is kept, the pose is refined once more jointly with those points, each
point placed by its reference observations and its query keypoint together
(``tracks.refine_with_points``): a point the references saw under a small angle is placed
along its rays no better than they allow, and the query's view of it helps. Kept unless fewer
points then fit within ``max_error_px``. Its figures on both dev sets:
``docs/benchmarks/2026-11-30-joint-refinement.md``.

The returned inlier masks are the matches within ``max_error_px`` Sampson error of the final
pose (the same definition as every other estimator); ``stats`` also reports the 2D–3D
inliers, and its ``score`` is their count.
"""

from __future__ import annotations

from services.estimators.base import FailureReason
from services.estimators.estimator import Estimator, Request, Solution
from services.estimators.tracks import (
    build_tracks,
    pose_from_tracks,
    refine_keeping_support,
    refine_with_points,
    triangulate_tracks,
)


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
        valid = tri.valid
        pose, refined = refine_keeping_support(
            found.pose,
            tri.points[valid],
            stacked.query_xy[tracks.query_match[valid]],
            request.query_camera,
            options,
            request.deadline,
        )
        stats["points_refined"] = float(refined)
        if refined:
            pose, joint = refine_with_points(
                stacked, tracks, tri, pose, request.query_camera, options, request.deadline
            )
            stats["points_joint"] = float(joint)
        return Solution(pose)
