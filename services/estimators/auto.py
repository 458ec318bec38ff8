"""``auto``: chooses, per query, which estimators to run, from the geometry the request shows
before any pose is estimated, and which of their verified poses to answer.

The plan (``plan_estimators``) has a first stage, whose estimators all run and whose verified
poses are compared, and fallbacks tried in order when none of them verifies:

- **forward motion** — the retrieved references lie on a line they look along (frames of a
  vehicle driving straight ahead, ``position_conditioning.ReferenceLayout``): the query's
  position along that line is unobservable for epipolar constraints, so E5+1 and the
  essential-matrix family are skipped. ``local_tri_all`` first; ``motion_averaging`` (whose last
  step is a 2D–3D refinement too) and, with depth for the query, ``e3p1`` (scale from depth) as
  fallbacks.
- **otherwise** — ``e5p1`` and ``local_tri_all`` both (E5+1 has the best accuracy for its time
  in Panek et al. 2025, "A Guide to Structureless Visual Localization", local triangulation the
  best accuracy; ``local_tri_all`` adds ~20 ms); ``motion_averaging`` then, with depth,
  ``e3p1`` as fallbacks. E5+1 answers ``degenerate_geometry`` by itself when the query turns
  out to lie on the line of the references.

Choosing between verified poses (``choose``): the pose of local triangulation, which ends on a
2D–3D refinement, is kept unless it has fewer than ``PREFER_RATIO`` times the epipolar inliers of
the other, or fewer than ``MIN_POINT_INLIER_SHARE`` of its triangulated points fit it — then its
triangulated structure went wrong (on redkitchen: four queries where ``local_tri_all`` was
0.4–1 m off with 11–16 % fewer inliers than ``e5p1``; with XFeat, a median share of 0.50 where
``local_tri_all`` alone missed (10 cm, 10°), 0.83 where both poses made it).
A pose of local triangulation whose points do not fit it is no answer on its own either: with
no other verified pose the query is not localized (``no_consensus``). On redkitchen (queries
0–499 against a map of frames 500–999, ``xfeat-lg``) one such pose of eight was right, six lay
1.5 m off at confidences up to 0.98; the fallback, run in their place, answered one of those
queries 1.5 m off too, so it is not run (``docs/benchmarks/2026-11-30-track-retrieval.md``).

When two or more poses verified, the answer's stats carry how far the others lie from it
(``agreement_stats``: ``auto_other_position_m``, ``auto_other_rotation_deg``, the largest over
the others): two estimators that agree are evidence for the pose, which the confidence model
reads (``services.confidence.model``).

Every pose goes through the 3D verification (``services.estimators.verification``); every
estimator gets what is left of the time budget. The answer names the estimator whose pose it is
and why (``EstimateResult.estimator_used`` and ``estimator_reason``); when every estimator
fails, the first one's failure is the answer.
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
from services.estimators.ransac import Deadline, searched_in_vain
from services.estimators.verification import verify_pose
from services.geometry.camera import Camera
from services.geometry.rigid import rotation_error_deg

# the roles of the plans, by the registry's names (``check_roles`` holds them against the
# registry when it builds auto): an epipolar estimator, first where the references
# spread around the query; local triangulation, which ends on a 2D–3D refinement and is
# preferred by ``choose``; motion averaging, the fallback (a 2D–3D refinement last too); and
# the fallback that needs depth (scale from depth), tried only when the request has some
EPIPOLAR = "e5p1"
TRIANGULATION = "local_tri_all"
AVERAGING = "motion_averaging"
DEPTH_SCALE = "e3p1"
ROLES = (EPIPOLAR, TRIANGULATION, AVERAGING, DEPTH_SCALE)

# local triangulation's pose is kept unless it has fewer epipolar inliers than this share of
# the other verified pose's, or fewer of its triangulated points fit it than this share
PREFER_RATIO = 0.97
MIN_POINT_INLIER_SHARE = 0.6


@dataclass(frozen=True)
class Plan:
    """What to run: ``first`` all, their verified poses compared; then ``fallbacks`` in order
    until one verifies; and why (a short sentence for the answer)."""

    first: tuple[str, ...]
    fallbacks: tuple[str, ...]
    reason: str

    @property
    def estimators(self) -> tuple[str, ...]:
        return self.first + self.fallbacks


def check_roles(candidates: Mapping[str, PoseEstimator]) -> None:
    """Check that every role of the plans names one of ``candidates`` (the registry's, which
    calls this as it builds ``auto``) with the ``needs_depth`` the plans assume: only
    ``DEPTH_SCALE`` needs depth.

    Raises:
        ValueError: a role names no candidate, or one that declares otherwise.
    """
    missing = [name for name in ROLES if name not in candidates]
    if missing:
        raise ValueError(f"auto's plans name estimators that are not registered: {missing}")
    wrong = [name for name in ROLES if candidates[name].needs_depth != (name == DEPTH_SCALE)]
    if wrong:
        raise ValueError(f"auto's plans assume otherwise of these estimators' depth: {wrong}")


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
    """What to run for a request with this reference layout, with or without depth."""
    depth_fallback = (DEPTH_SCALE,) if depth else ()
    if layout.forward_motion:
        return Plan(
            (TRIANGULATION,),
            (AVERAGING, *depth_fallback),
            f"forward motion: reference centres on a line (collinearity "
            f"{layout.collinearity:.2f}) {layout.line_view_angle_deg:.0f}° from their viewing "
            "direction, where epipolar constraints leave the position along it unobservable",
        )
    return Plan(
        (EPIPOLAR, TRIANGULATION),
        (AVERAGING, *depth_fallback),
        f"references spread around the query (collinearity {layout.collinearity:.2f})",
    )


def choose(verified: dict[str, EstimateResult]) -> tuple[str, str]:
    """The name of the verified pose to answer (``verified`` non-empty) and why."""
    if len(verified) == 1:
        return next(iter(verified)), "the only verified pose"
    others = {name: r for name, r in verified.items() if name != TRIANGULATION}
    best = max(others, key=lambda name: others[name].num_inliers)
    if TRIANGULATION not in verified:
        return best, "the most inliers"
    local, other = verified[TRIANGULATION].num_inliers, others[best].num_inliers
    if local < PREFER_RATIO * other:
        return best, f"{other} inliers vs {TRIANGULATION}'s {local}: its triangulation went wrong"
    share = point_inlier_share(verified[TRIANGULATION])
    if share < MIN_POINT_INLIER_SHARE:
        return best, f"{share:.0%} of {TRIANGULATION}'s triangulated points fit its pose"
    return TRIANGULATION, f"2D–3D refined, {local} inliers vs {best}'s {other}"


def point_inlier_share(result: EstimateResult) -> float:
    """The share of local triangulation's triangulated points that are inliers of its pose
    (1 when its stats do not say)."""
    triangulated = result.stats.get("points_triangulated", 0.0)
    if triangulated <= 0:
        return 1.0
    return result.stats.get("points_inliers", triangulated) / triangulated


def agreement_stats(verified: dict[str, EstimateResult], chosen: str) -> dict[str, float]:
    """How far the other verified poses lie from ``chosen``'s: ``auto_verified_poses`` and,
    with another pose, ``auto_other_position_m`` (camera centres, map units) and
    ``auto_other_rotation_deg``, each the largest over the others."""
    stats = {"auto_verified_poses": float(len(verified))}
    pose = verified[chosen].cam_from_world
    others = [r.cam_from_world for n, r in verified.items() if n != chosen]
    others_posed = [o for o in others if o is not None]
    if pose is None or not others_posed:
        return stats
    stats["auto_other_position_m"] = max(
        float(np.linalg.norm(o.center - pose.center)) for o in others_posed
    )
    stats["auto_other_rotation_deg"] = max(
        rotation_error_deg(o.rotation, pose.rotation) for o in others_posed
    )
    return stats


class AutoEstimator:
    """Runs the estimators of ``plan_estimators`` and answers the pose ``choose`` keeps.

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

        def attempt(name: str) -> EstimateResult:
            """``name``'s pose, verified, with what is left of the budget."""
            left = deadline.remaining_s()
            budget = replace(options, time_budget_s=None if left == float("inf") else left)
            found = self.candidates[name].estimate(query_camera, references, budget)
            if found.cam_from_world is not None and deadline.expired():
                # not verified in time: no answer (100 references: verifying takes ~0.5 s)
                return EstimateResult.failure(
                    FailureReason.TIME_BUDGET_EXCEEDED, references, found.stats
                )
            return verify_pose(found, query_camera, references, budget, deadline)

        results: dict[str, EstimateResult] = {}
        if options.spread is not None and len(plan.first) > 1 and not deadline.expired():
            # the first stage's estimators are independent: at once where a worker is idle
            done = options.spread(lambda names: [attempt(n) for n in names], plan.first)
            results.update(zip(plan.first, done, strict=True))
        for name in plan.estimators:
            if name in results:
                continue
            if deadline.expired() or (
                name in plan.fallbacks
                and (self._verified(results) or self._in_vain(results, plan, options))
            ):
                break
            results[name] = attempt(name)
        attempts = {"auto_attempts": float(len(results))}
        verified = self._verified(results)
        if self._fit(results):
            name, why = choose(verified)
            failed = [f"{n} {r.failure_reason}" for n, r in results.items() if n not in verified]
            tried = f"; failed: {', '.join(failed)}" if failed else ""
            return replace(
                verified[name],
                stats=verified[name].stats | attempts | agreement_stats(verified, name),
                estimator_used=name,
                estimator_reason=f"{plan.reason}; {name}: {why}{tried}",
            )
        first_name = plan.estimators[0]
        first = results.get(first_name) or EstimateResult.failure(
            FailureReason.TIME_BUDGET_EXCEEDED, references
        )
        if first.cam_from_world is not None:  # local triangulation's, its points unfit
            first = EstimateResult.failure(FailureReason.NO_CONSENSUS, references, first.stats)
        unfit = [
            f"; {name}: {point_inlier_share(r):.0%} of its triangulated points fit its pose"
            for name, r in verified.items()
        ]
        return replace(
            first,
            stats=first.stats | attempts,
            estimator_used=first_name,
            estimator_reason=f"{plan.reason}; no estimator localized "
            f"({', '.join(results) or 'none ran'}){''.join(unfit)}",
        )

    @staticmethod
    def _in_vain(results: dict[str, EstimateResult], plan: Plan, options: EstimatorOptions) -> bool:
        """The plan's first estimator, whose failure ``auto`` answers when none localizes,
        drew every hypothesis it may without a pose (``searched_in_vain``): an image of
        nothing in the map, where a fallback on the same matches finds nothing either (no
        fallback answered a query on either development set)."""
        first = results.get(plan.first[0])
        return (
            first is not None
            and first.cam_from_world is None
            and searched_in_vain(first.stats, options.ransac)
        )

    @staticmethod
    def _verified(results: dict[str, EstimateResult]) -> dict[str, EstimateResult]:
        return {name: r for name, r in results.items() if r.cam_from_world is not None}

    @classmethod
    def _fit(cls, results: dict[str, EstimateResult]) -> dict[str, EstimateResult]:
        """The verified poses but local triangulation's when fewer than
        ``MIN_POINT_INLIER_SHARE`` of its triangulated points fit it: its structure went
        wrong, and alone it is no answer."""
        return {
            name: r
            for name, r in cls._verified(results).items()
            if name != TRIANGULATION or point_inlier_share(r) >= MIN_POINT_INLIER_SHARE
        }
