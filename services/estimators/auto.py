"""``auto``: chooses, per query, which estimators to run and in which order, from the geometry
the request shows before any pose is estimated, and keeps the first pose that verifies in 3D.

The plan (``plan_estimators``):

- **forward motion** — the retrieved references lie on a line they look along (frames of a
  vehicle driving straight ahead, ``position_conditioning.ReferenceLayout``): the query's
  position along that line is unobservable for epipolar constraints, so E5+1 and the
  essential-matrix family are skipped; local triangulation (``local_tri_all``) comes first,
  motion averaging (whose final step is a 2D–3D refinement too) second. With depth for the
  query and the references, ``e3p1`` (whose scale comes from depth, not from baselines) is the
  last resort.
- **depth present** (the query and some references) — ``e3p1`` first (its scale comes from
  depth), then ``local_tri_all``.
- **otherwise** — ``e5p1`` first (the best accuracy for its time in Panek et al. 2025, "A Guide
  to Structureless Visual Localization"; it answers ``degenerate_geometry`` by itself when the
  query turns out to lie on the line of the references), then ``local_tri_all``, then
  ``motion_averaging``.

Each candidate's pose goes through the 3D verification (``services.verification``) before the
next is tried; every candidate gets what is left of the time budget. The answer names the
estimator whose pose it is and why it was chosen (``EstimateResult.estimator_used`` and
``estimator_reason``); when every candidate fails, the first one's failure is the answer.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from services.estimators.base import (
    EstimateResult,
    FailureReason,
    PoseEstimator,
    ReferenceObservation,
)
from services.estimators.estimator import precheck
from services.estimators.options import EstimatorOptions
from services.estimators.position_conditioning import ReferenceLayout, reference_layout
from services.estimators.ransac import Deadline
from services.geometry.camera import Camera
from services.verification import verify_pose


@dataclass(frozen=True)
class Plan:
    """The estimators to try, in order, and why (a short sentence for the answer)."""

    estimators: tuple[str, ...]
    reason: str


def has_depth(references: list[ReferenceObservation]) -> bool:
    """The query has depth at some matched keypoint and so has some reference."""

    def any_positive(values: object) -> bool:
        return values is not None and bool(np.any(np.asarray(values) > 0))

    return any(any_positive(ref.query_depth) for ref in references) and any(
        any_positive(ref.reference_depth) for ref in references
    )


def layout_of(references: list[ReferenceObservation]) -> ReferenceLayout:
    """The layout of the references that have matches, weighted by their match counts."""
    return reference_layout(
        np.stack([ref.cam_from_world.center for ref in references]),
        np.stack([ref.cam_from_world.rotation[2] for ref in references]),
        np.array([float(ref.num_matches) for ref in references]),
    )


def plan_estimators(layout: ReferenceLayout, depth: bool) -> Plan:
    """The order of estimators for a request with this reference layout and depth."""
    if layout.forward_motion:
        shape = (
            f"forward motion: reference centres on a line (collinearity "
            f"{layout.collinearity:.2f}) {layout.line_view_angle_deg:.0f}° from their viewing "
            "direction, where epipolar constraints leave the position along it unobservable"
        )
        fallback = ("e3p1",) if depth else ()
        return Plan(("local_tri_all", "motion_averaging", *fallback), shape)
    if depth:
        return Plan(
            ("e3p1", "local_tri_all"),
            "depth for the query and the references: scale from depth",
        )
    return Plan(
        ("e5p1", "local_tri_all", "motion_averaging"),
        f"references spread around the query (collinearity {layout.collinearity:.2f})",
    )


class AutoEstimator:
    """Runs the estimators of ``plan_estimators`` in order until one's pose verifies.

    Args:
        candidates: the estimators by name (the registry's), which the plans refer to.
    """

    name = "auto"
    needs_depth = False

    def __init__(self, candidates: Mapping[str, PoseEstimator]) -> None:
        self.candidates = dict(candidates)

    def estimate(
        self,
        query_camera: Camera,
        references: list[ReferenceObservation],
        options: EstimatorOptions,
    ) -> EstimateResult:
        reason = precheck(references, min_matches=1)
        if reason is not None:
            return replace(
                EstimateResult.failure(reason, references),
                estimator_used=self.name,
                estimator_reason="no estimator ran",
            )
        deadline = Deadline(options.time_budget_s)
        plan = plan_estimators(layout_of(references), has_depth(references))
        first = replace(
            EstimateResult.failure(FailureReason.TIME_BUDGET_EXCEEDED, references),
            estimator_used=plan.estimators[0],
        )
        for position, name in enumerate(plan.estimators):
            if deadline.expired():
                break
            left = deadline.remaining_s()
            budget = replace(options, time_budget_s=None if left == float("inf") else left)
            result = verify_pose(
                self.candidates[name].estimate(query_camera, references, budget),
                query_camera,
                references,
                budget,
            )
            stats = {**result.stats, "auto_attempts": float(position + 1)}
            if result.cam_from_world is not None:
                why = plan.reason
                if position > 0:
                    tried = ", ".join(plan.estimators[:position])
                    why = f"{why}; {tried} failed (first: {first.failure_reason})"
                return replace(result, stats=stats, estimator_used=name, estimator_reason=why)
            if position == 0:
                first = replace(result, stats=stats, estimator_used=name)
        return replace(
            first,
            estimator_reason=f"{plan.reason}; no estimator localized "
            f"({', '.join(plan.estimators)})",
        )
