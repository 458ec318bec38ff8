"""Pose approximation (the baseline of Panek et al. 2025, "A Guide to Structureless Visual
Localization"): the query pose is the top-1 retrieved pose, or a retrieval-score-weighted
interpolation of the retrieved poses (default).

Weighted mode: weights are the retrieval scores clipped at 0 (uniform when all are ≤ 0); the
centre is the weighted mean of the reference centres and the rotation the chordal L2 mean of
the reference rotations (projected back onto SO(3)). No correspondences are used, so every
inlier mask is empty and the confidence stays low (≤ 0.1).
"""

from __future__ import annotations

import numpy as np

from services.errors import InvalidInputError
from services.estimators.base import EstimateResult, FailureReason, ReferenceObservation
from services.estimators.estimator import Estimator, Request, Solution, precheck
from services.estimators.options import PoseApproxMode
from services.geometry.averaging import project_to_rotation
from services.geometry.rigid import Rigid3d


class PoseApproxEstimator(Estimator):
    name = "pose_approx"

    def check(self, references: list[ReferenceObservation]) -> FailureReason | None:
        return precheck(references, min_matches=0, min_pairs=1)

    def solve(self, request: Request) -> Solution:
        references, options = request.references, request.options
        try:
            mode = PoseApproxMode(options.pose_approx.mode)
        except ValueError:
            known = ", ".join(PoseApproxMode)
            raise InvalidInputError(
                f"unknown pose_approx mode {options.pose_approx.mode!r}; known: {known}"
            ) from None
        scores = np.array([ref.retrieval_score for ref in references], dtype=np.float64)
        rotations = np.stack([ref.cam_from_world.rotation for ref in references])
        centers = np.stack([ref.cam_from_world.center for ref in references])
        if mode is PoseApproxMode.TOP1:
            best = int(np.argmax(scores))
            weights = np.zeros(len(references))
            weights[best] = 1.0
        else:
            weights = np.clip(scores, 0.0, None)
            if weights.sum() <= 0:
                weights = np.ones(len(references))
        weights = weights / weights.sum()
        R = project_to_rotation(np.einsum("n,nij->ij", weights, rotations))
        C = weights @ centers
        return Solution(Rigid3d(R, -R @ C))

    def result(self, request: Request, solution: Solution) -> EstimateResult:
        """No correspondences used: empty inlier masks, a confidence of at most 0.1."""
        references = request.references
        best_score = max(ref.retrieval_score for ref in references)
        masks = [np.zeros(ref.num_matches, dtype=bool) for ref in references]
        stats = {
            "iterations": 0.0,
            "num_references": float(len(references)),
            "inlier_ratio": 0.0,
            "score": float(best_score),
        }
        confidence = float(0.1 * np.clip(best_score, 0.0, 1.0))
        return EstimateResult(solution.pose, masks, confidence, stats, None)
