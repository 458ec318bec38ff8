"""Pose triangulation with depth: as ``essential_5pt``, but each query–reference relative pose
comes from the 3-point-with-depth solver (``depth_relative_pose``) in LO-RANSAC. Depths may be
known up to one scale per image (the solver fits a similarity), so monocular depth works too.
Matches without depth (0) still count in scoring and refinement; pairs without any depth
arrays are skipped: with depth for fewer than two references the result is ``too_few_matches``
(without any, ``missing_depth``)."""

from __future__ import annotations

from services.estimators.base import FailureReason, ReferenceObservation
from services.estimators.pose_triangulation import PoseTriangulationEstimator, solve_3pt_depth


class Essential3ptDepthEstimator(PoseTriangulationEstimator):
    name = "essential_3pt_depth"
    needs_depth = True

    def __init__(self) -> None:
        super().__init__(solve_3pt_depth)

    def check(self, references: list[ReferenceObservation]) -> FailureReason | None:
        with_depth = [
            ref
            for ref in references
            if ref.query_depth is not None and ref.reference_depth is not None
        ]
        if references and len(with_depth) < 2:
            return FailureReason.TOO_FEW_MATCHES
        return super().check(references)
