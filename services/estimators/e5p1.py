"""E5+1: semi-generalized relative pose with PoseLib (Zheng & Wu 2015; the guide's default).

The retrieved references form a generalized camera whose rig frame is the world frame; the
query is a single pinhole camera. PoseLib's 5+1 solver in LO-RANSAC (with Sampson-error
refinement) gives the query's ``cam_from_world`` directly, metric scale from the references'
known baselines.

Speed: LO-RANSAC's cost is its iterations (at least ``min_iterations``, the guide's 1000)
times the correspondences each hypothesis is scored on. The hypotheses are therefore scored
on a seeded random sample of at most ``RANSAC_SAMPLE_PER_PAIR`` matches per reference; the
winning pose is then re-scored and refined on every match (generalized Sampson refinement,
``pose_triangulation.local_optimisation``), so the answer's inliers and accuracy come from all
of them. At the guide's setting (10 references × 1000 matches) this is ~4× faster for the same
accuracy (``python -m tools.benchmarks.estimators``).

The pipeline then verifies the pose in 3D (``services.estimators.verification``).
"""

from __future__ import annotations

import numpy as np
import poselib

from services.estimators.base import (
    EstimateResult,
    EstimatorOptions,
    FailureReason,
    ReferenceObservation,
)
from services.estimators.correspondences import Deadline, finish, random_subset, stack_matches
from services.estimators.pose_triangulation import local_optimisation
from services.estimators.poselib_bridge import from_poselib, ransac_options, to_poselib
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d

RANSAC_SAMPLE_PER_PAIR = 100  # matches per reference that RANSAC hypotheses are scored on


class E5p1Estimator:
    name = "e5p1"

    def estimate(
        self,
        query_camera: Camera,
        references: list[ReferenceObservation],
        options: EstimatorOptions,
    ) -> EstimateResult:
        used = [i for i, ref in enumerate(references) if ref.num_matches > 0]
        # PoseLib 2.0.5 loops forever with fewer than two non-empty pairs or no pair of >= 5
        # matches (DESIGN.md "Known pitfalls"): never call it then.
        if len(used) < 2 or max(references[i].num_matches for i in used) < 5:
            return EstimateResult.failure(FailureReason.TOO_FEW_MATCHES, references)
        centers = np.stack([references[i].cam_from_world.center for i in used])
        if np.ptp(centers, axis=0).max() < 1e-9:
            return EstimateResult.failure(FailureReason.DEGENERATE_GEOMETRY, references)

        rng = np.random.default_rng(options.seed)
        matches = []
        for pair_index, i in enumerate(used):
            ref = references[i]
            sample = random_subset(ref.num_matches, RANSAC_SAMPLE_PER_PAIR, rng)
            m = poselib.PairwiseMatches()
            m.cam_id1 = pair_index
            m.cam_id2 = 0
            m.x1 = np.ascontiguousarray(ref.reference_xy[sample], dtype=np.float64)
            m.x2 = np.ascontiguousarray(ref.query_xy[sample], dtype=np.float64)
            matches.append(m)
        deadline = Deadline(options.time_budget_s)
        if deadline.expired():
            return EstimateResult.failure(FailureReason.TIME_BUDGET_EXCEEDED, references)
        # iterations capped by the remaining time budget, if any
        ransac = ransac_options(
            options,
            deadline,
            epipolar_px=options.max_error_px,
            num_matches=sum(len(m.x1) for m in matches),
        )
        pose, info = poselib.estimate_generalized_relative_pose(
            matches,
            [to_poselib(references[i].cam_from_world) for i in used],
            [references[i].camera.to_poselib() for i in used],
            [to_poselib(Rigid3d.identity())],
            [query_camera.to_poselib()],
            ransac,
            {},
        )
        stats = {"iterations": float(info.get("iterations", 0))}
        hypothesis = from_poselib(pose)
        if not np.all(np.isfinite(hypothesis.matrix)):
            return EstimateResult.failure(FailureReason.NO_CONSENSUS, references, stats)
        stacked = stack_matches(query_camera, references)
        cam_from_world, inliers = local_optimisation(
            hypothesis,
            stacked,
            references,
            query_camera,
            options,
            deadline,
            rounds=2,
            refine_iterations=10,
        )
        stats["score"] = float(inliers.sum())
        return finish(cam_from_world, stacked.split(inliers), references, options, stats)
