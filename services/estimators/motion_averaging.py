"""LazyLoc-style motion averaging: 5-point relative poses per pair (PoseLib), robust rotation
averaging (geodesic L1 median, then chordal mean of the inliers within 5°) and translation
averaging (IRLS with Cauchy weights on the ray angles, rays beyond 10° rejected), then the
averaged pose is refined on 2D–3D matches: query keypoints ↔ points triangulated between the
retrieved references through the shared query keypoints (RANSAC triangulation, threshold
``triangulation_error_px``), by PoseLib absolute-pose refinement on the points that reproject
within an adaptive threshold ≤ ``max_error_px`` (three rounds, ``tracks.refine_on_points``).
Without enough triangulated points the averaged pose is returned as is
(``stats["refined"] = 0``).

Speed (the guide's LazyLoc takes 101 ms a query): the pairwise relative poses are only
proposals that robust averaging filters, so each pair's RANSAC scores its hypotheses on a
sample of ``PAIR_SAMPLE`` matches and stops adaptively (PoseLib's success probability) after
at least ``PAIR_MIN_ITERATIONS`` instead of the final estimators' ``min_iterations``; the
refinement triangulates at most ``MAX_REFINEMENT_TRACKS`` tracks, sampled at random.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

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
    random_subset,
    stack_matches,
)
from services.estimators.pose_triangulation import (
    pairwise_poses,
    sampled_solver,
    solve_5pt,
    triangulate_pose,
)
from services.estimators.tracks import build_tracks, refine_on_points, triangulate_tracks
from services.geometry.camera import Camera

REFINEMENT_ROUNDS = 4
COARSE_FACTOR = 8.0  # the first refinement round takes points within 8 × max_error_px
MIN_POINTS = 6  # fewer inlier 2D–3D matches: keep the averaged pose
PAIR_SAMPLE = 64  # matches per pair that the pairwise RANSAC scores hypotheses on
PAIR_MIN_ITERATIONS = 100  # least pairwise RANSAC iterations (then adaptive stopping)
MAX_REFINEMENT_TRACKS = 300  # tracks triangulated for the refinement


class MotionAveragingEstimator:
    name = "motion_averaging"

    def estimate(
        self,
        query_camera: Camera,
        references: list[ReferenceObservation],
        options: EstimatorOptions,
    ) -> EstimateResult:
        deadline = Deadline(options.time_budget_s)
        reason = precheck(references, min_matches=5)
        if reason is not None:
            return EstimateResult.failure(reason, references)
        pair_options = replace(
            options, min_iterations=min(options.min_iterations, PAIR_MIN_ITERATIONS)
        )
        pairs, timed_out = pairwise_poses(
            query_camera, references, pair_options, deadline, sampled_solver(solve_5pt, PAIR_SAMPLE)
        )
        stats: dict[str, float] = {
            "iterations": float(sum(p.iterations for p in pairs)),
            "pairs_with_relative_pose": float(len(pairs)),
        }
        if timed_out:
            return EstimateResult.failure(FailureReason.TIME_BUDGET_EXCEEDED, references, stats)
        if len(pairs) < 2:
            return EstimateResult.failure(FailureReason.NO_CONSENSUS, references, stats)
        averaged = triangulate_pose(pairs, references, robust="irls")
        stats["pairs_consistent"] = float(averaged.pair_inliers.sum())
        if averaged.pose is None:
            return EstimateResult.failure(
                averaged.failure or FailureReason.NO_CONSENSUS, references, stats
            )
        pose = averaged.pose
        stacked = stack_matches(query_camera, references)
        tracks = build_tracks(stacked, options.track_merge_px)
        sub = tracks.multi_view()
        rng = np.random.default_rng(options.seed)
        sub = sub.subset(random_subset(sub.size, MAX_REFINEMENT_TRACKS, rng))
        stats["refined"] = 0.0
        if sub.size >= MIN_POINTS and not deadline.expired():
            tri = triangulate_tracks(stacked, sub, options.triangulation_error_px)
            points = tri.points[tri.valid]
            query_xy = stacked.query_xy[sub.query_match[tri.valid]]
            stats["points_triangulated"] = float(points.shape[0])
            pose, used = refine_on_points(
                pose,
                points,
                query_xy,
                query_camera,
                options,
                deadline,
                REFINEMENT_ROUNDS,
                MIN_POINTS,
                initial_px=COARSE_FACTOR * options.max_error_px,
            )
            stats["refined"] = float(used > 0)
            stats["points_inliers"] = float(used)
        errors = pose_sampson_errors_px(stacked, pose.rotation[None], pose.center[None])[0]
        inliers = errors < options.max_error_px
        stats["score"] = float(inliers.sum())
        return finish(pose, stacked.split(inliers), references, options, stats)
