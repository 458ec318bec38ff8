"""Essential-matrix pose triangulation ("Ess. mat." in Panek et al. 2025, "A Guide to Structureless
Visual Localization"): a 5-point essential matrix per query–reference pair (PoseLib LO-RANSAC),
robust rotation averaging of the implied query rotations, camera-centre triangulation from the
translation directions (RANSAC over pairs, least squares over the inlier rays), then generalized
Sampson refinement over all pairs. See ``pose_triangulation`` for the steps."""

from __future__ import annotations

from services.estimators.pose_triangulation import PoseTriangulationEstimator, solve_5pt


class Essential5ptEstimator(PoseTriangulationEstimator):
    name = "essential_5pt"
    position_from_baselines = True

    def __init__(self) -> None:
        super().__init__(solve_5pt)
