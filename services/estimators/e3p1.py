"""E3+1: semi-generalized relative pose with depth. LO-RANSAC over all pairs at once, one full
query pose per minimal sample: three matches with depth (metric depths), or three matches
with depth in one reference plus one match of another (depths up to one scale per image,
``E3p1Options.metric_depth = False``); see ``generalized_depth_pose``. Inlier masks: matches
within ``max_error_px`` Sampson error."""

from __future__ import annotations

from services.estimators.base import FailureReason
from services.estimators.estimator import Estimator, Request, Solution
from services.estimators.generalized_depth_pose import ransac_query_pose_depth


class E3p1Estimator(Estimator):
    name = "e3p1"
    needs_depth = True

    def solve(self, request: Request) -> Solution:
        found = ransac_query_pose_depth(request)
        request.stats["iterations"] = float(found.iterations)
        if found.model is None:
            request.fail_if_expired()
            request.fail(FailureReason.NO_CONSENSUS)
        return Solution(found.model, found.inliers)
