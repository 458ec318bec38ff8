"""LazyLoc-style motion averaging: 5-point relative poses per pair (PoseLib), robust rotation
averaging (geodesic L1 median, then chordal mean of the inliers within 5°) and translation averaging
(IRLS with Cauchy weights on the ray angles, rays beyond 10° rejected), then the averaged pose is
refined on 2D–3D matches: query keypoints ↔ points triangulated between the retrieved references
through the shared query keypoints (RANSAC triangulation, threshold
``TriangulationOptions.max_error_px``), by PoseLib absolute-pose refinement on the points that
reproject within an adaptive threshold ≤ ``max_error_px`` (three rounds,
``tracks.refine_on_points``). Without enough triangulated points the averaged pose is returned as is
(``stats["refined"] = 0``).

Speed (LazyLoc takes 101 ms a query on a CPU in Panek et al. 2025, "A Guide to Structureless Visual
Localization"): the pairwise relative poses are only proposals that robust averaging filters, so
each pair's RANSAC scores its hypotheses on a sample of ``PAIR_SAMPLE`` matches and stops adaptively
(PoseLib's success probability) after at least ``PAIR_MIN_ITERATIONS`` instead of the final
estimators' ``min_iterations``; the refinement triangulates at most ``MAX_REFINEMENT_TRACKS``
tracks, sampled at random.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from services.estimators.correspondences import random_subset
from services.estimators.estimator import Estimator, Request, Solution
from services.estimators.pose_triangulation import sampled_solver, solve_5pt, triangulated_pose
from services.estimators.tracks import build_tracks, refine_on_points, triangulate_tracks

REFINEMENT_ROUNDS = 4
COARSE_FACTOR = 8.0  # the first refinement round takes points within 8 × max_error_px
MIN_POINTS = 6  # fewer inlier 2D–3D matches: keep the averaged pose
PAIR_SAMPLE = 64  # matches per pair that the pairwise RANSAC scores hypotheses on
PAIR_MIN_ITERATIONS = 100  # least pairwise RANSAC iterations (then adaptive stopping)
MAX_REFINEMENT_TRACKS = 300  # tracks triangulated for the refinement


class MotionAveragingEstimator(Estimator):
    name = "motion_averaging"

    def solve(self, request: Request) -> Solution:
        options, stats = request.options, request.stats
        ransac = options.ransac
        pair_options = replace(
            options,
            ransac=replace(ransac, min_iterations=min(ransac.min_iterations, PAIR_MIN_ITERATIONS)),
        )
        pose = triangulated_pose(
            request, sampled_solver(solve_5pt, PAIR_SAMPLE), "irls", pair_options
        )
        stacked = request.stacked
        tracks = build_tracks(stacked, options.triangulation.track_merge_px)
        sub = tracks.multi_view()
        rng = np.random.default_rng(ransac.seed)
        sub = sub.subset(random_subset(sub.size, MAX_REFINEMENT_TRACKS, rng))
        stats["refined"] = 0.0
        if sub.size >= MIN_POINTS and not request.deadline.expired():
            tri = triangulate_tracks(
                stacked, sub, options.triangulation.max_error_px, deadline=request.deadline
            )
            points = tri.points[tri.valid]
            query_xy = stacked.query_xy[sub.query_match[tri.valid]]
            stats["points_triangulated"] = float(points.shape[0])
            pose, used = refine_on_points(
                pose,
                points,
                query_xy,
                request.query_camera,
                options,
                request.deadline,
                REFINEMENT_ROUNDS,
                MIN_POINTS,
                initial_px=COARSE_FACTOR * ransac.max_error_px,
            )
            stats["refined"] = float(used > 0)
            stats["points_inliers"] = float(used)
        return Solution(pose)
