"""Essential-matrix pose triangulation ("Ess. mat." in the guide): a 5-point essential matrix
per query–reference pair (PoseLib LO-RANSAC), robust rotation averaging of the implied query
rotations, camera-centre triangulation from the translation directions (RANSAC over pairs,
least squares over the inlier rays), then generalized Sampson refinement over all pairs.
See ``pose_triangulation`` for the steps."""

from __future__ import annotations

from services.estimators.base import EstimateResult, EstimatorOptions, ReferenceObservation
from services.estimators.pose_triangulation import estimate_by_pose_triangulation, solve_5pt
from services.geometry.camera import Camera


class Essential5ptEstimator:
    name = "essential_5pt"

    def estimate(
        self,
        query_camera: Camera,
        references: list[ReferenceObservation],
        options: EstimatorOptions,
    ) -> EstimateResult:
        return estimate_by_pose_triangulation(query_camera, references, options, solve_5pt)
