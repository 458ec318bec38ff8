"""E5+1: semi-generalized relative pose with PoseLib (Zheng & Wu 2015; the guide's default).

The retrieved references form a generalized camera whose rig frame is the world frame; the
query is a single pinhole camera. PoseLib's 5+1 solver in LO-RANSAC (with Sampson-error
refinement) gives the query's ``cam_from_world`` directly, metric scale from the references'
known baselines.

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
    confidence_from_inliers,
)
from services.estimators.correspondences import Deadline
from services.estimators.poselib_bridge import ransac_options
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d


def _poselib_pose(pose: Rigid3d) -> poselib.CameraPose:
    out = poselib.CameraPose()
    out.q = pose.quaternion
    out.t = pose.translation
    return out


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

        matches = []
        for pair_index, i in enumerate(used):
            m = poselib.PairwiseMatches()
            m.cam_id1 = pair_index
            m.cam_id2 = 0
            m.x1 = np.ascontiguousarray(references[i].reference_xy, dtype=np.float64)
            m.x2 = np.ascontiguousarray(references[i].query_xy, dtype=np.float64)
            matches.append(m)
        deadline = Deadline(options.time_budget_s)
        if deadline.expired():
            return EstimateResult.failure(FailureReason.TIME_BUDGET_EXCEEDED, references)
        # iterations capped by the remaining time budget, if any
        ransac = ransac_options(
            options,
            deadline,
            epipolar_px=options.max_error_px,
            num_matches=sum(references[i].num_matches for i in used),
        )
        pose, info = poselib.estimate_generalized_relative_pose(
            matches,
            [_poselib_pose(references[i].cam_from_world) for i in used],
            [references[i].camera.to_poselib() for i in used],
            [_poselib_pose(Rigid3d.identity())],
            [query_camera.to_poselib()],
            ransac,
            {},
        )
        masks = [np.zeros(ref.num_matches, dtype=bool) for ref in references]
        for pair_index, i in enumerate(used):
            masks[i] = np.asarray(info["inliers"][pair_index], dtype=bool)
        num_inliers = int(sum(int(m.sum()) for m in masks))
        refs_with_inliers = sum(int(m.sum() >= 3) for m in masks)
        total = sum(ref.num_matches for ref in references)
        stats = {
            "iterations": float(info.get("iterations", 0)),
            "num_matches": float(total),
            "inlier_ratio": num_inliers / max(total, 1),
            "references_with_inliers": float(refs_with_inliers),
        }
        if num_inliers < options.min_inliers or refs_with_inliers < options.min_references:
            return EstimateResult(None, masks, 0.0, stats, FailureReason.NO_CONSENSUS)
        cam_from_world = Rigid3d.from_quaternion(np.asarray(pose.q), np.asarray(pose.t))
        if not (
            np.all(np.isfinite(cam_from_world.rotation))
            and np.all(np.isfinite(cam_from_world.translation))
        ):
            return EstimateResult(None, masks, 0.0, stats, FailureReason.NO_CONSENSUS)
        confidence = confidence_from_inliers(num_inliers, refs_with_inliers)
        return EstimateResult(cam_from_world, masks, confidence, stats, None)
