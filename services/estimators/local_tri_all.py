"""Local triangulation over all references ("SfM on the fly", the guide's most accurate
family): tracks through each query keypoint, RANSAC triangulation of every track over all
retrieved references (threshold ``triangulation_error_px``: 2 px sparse, 8 px dense), then
P3P LO-RANSAC with refinement (PoseLib) on the query keypoints ↔ triangulated points.

The returned inlier masks are the matches within ``max_error_px`` Sampson error of the final
pose (the same definition as every other estimator); ``stats`` also reports the 2D–3D
inliers.
"""

from __future__ import annotations

from services.estimators.base import (
    EstimateResult,
    EstimatorOptions,
    FailureReason,
    ReferenceObservation,
)
from services.estimators.correspondences import (
    Deadline,
    finish,
    pose_sampson_errors_px,
    precheck,
    stack_matches,
)
from services.estimators.tracks import build_tracks, pose_from_tracks, triangulate_tracks
from services.geometry.camera import Camera


class LocalTriAllEstimator:
    name = "local_tri_all"

    def estimate(
        self,
        query_camera: Camera,
        references: list[ReferenceObservation],
        options: EstimatorOptions,
    ) -> EstimateResult:
        deadline = Deadline(options.time_budget_s)
        reason = precheck(references, min_matches=1)
        if reason is not None:
            return EstimateResult.failure(reason, references)
        stacked = stack_matches(query_camera, references)
        all_tracks = build_tracks(stacked, options.track_merge_px)
        tracks = all_tracks.multi_view()
        stats: dict[str, float] = {
            "tracks": float(all_tracks.size),
            "tracks_multi_view": float(tracks.size),
        }
        if tracks.size < 4:
            return EstimateResult.failure(FailureReason.TOO_FEW_MATCHES, references, stats)
        tri = triangulate_tracks(stacked, tracks, options.triangulation_error_px)
        stats["points_triangulated"] = float(tri.valid.sum())
        if deadline.expired():
            return EstimateResult.failure(FailureReason.TIME_BUDGET_EXCEEDED, references, stats)
        if tri.valid.sum() < 4:
            reason = FailureReason.DEGENERATE_GEOMETRY if tracks.size >= 20 else None
            return EstimateResult.failure(
                reason or FailureReason.TOO_FEW_MATCHES, references, stats
            )
        found = pose_from_tracks(stacked, tracks, tri, query_camera, options, deadline)
        if found is None:
            return EstimateResult.failure(FailureReason.NO_CONSENSUS, references, stats)
        stats["iterations"] = float(found.iterations)
        stats["points_inliers"] = float(found.inliers.sum())
        stats["score"] = float(found.inliers.sum())
        pose = found.pose
        errors = pose_sampson_errors_px(stacked, pose.rotation[None], pose.center[None])[0]
        masks = stacked.split(errors < options.max_error_px)
        if found.inliers.sum() < 4:
            return EstimateResult(None, masks, 0.0, stats, FailureReason.NO_CONSENSUS)
        return finish(pose, masks, references, options, stats)
