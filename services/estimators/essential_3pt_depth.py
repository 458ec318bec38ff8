"""Pose triangulation with depth: as ``essential_5pt``, but each query–reference relative pose
comes from the 3-point-with-depth solver (``depth_relative_pose``) in LO-RANSAC. Depths may be
known up to one scale per image (the solver fits a similarity), so monocular depth works too.
Matches without depth (0) still count in scoring and refinement; pairs without any depth
arrays are skipped, so without depth the result is ``too_few_matches`` / ``no_consensus``."""

from __future__ import annotations

from services.estimators.base import (
    EstimateResult,
    EstimatorOptions,
    FailureReason,
    ReferenceObservation,
)
from services.estimators.pose_triangulation import (
    estimate_by_pose_triangulation,
    solve_3pt_depth,
)
from services.geometry.camera import Camera


class Essential3ptDepthEstimator:
    name = "essential_3pt_depth"

    def estimate(
        self,
        query_camera: Camera,
        references: list[ReferenceObservation],
        options: EstimatorOptions,
    ) -> EstimateResult:
        with_depth = [
            ref
            for ref in references
            if ref.query_depth is not None and ref.reference_depth is not None
        ]
        if references and len(with_depth) < 2:
            return EstimateResult.failure(FailureReason.TOO_FEW_MATCHES, references)
        return estimate_by_pose_triangulation(query_camera, references, options, solve_3pt_depth)
