"""What every estimator does around its own method: input checks, the time budget, the stacked
matches, failures, and the finishing (inliers within ``max_error_px`` Sampson error of the
pose, acceptance, confidence). A method subclasses ``Estimator`` and writes ``solve``."""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from functools import cached_property
from typing import NoReturn

import numpy as np

from services.estimators.base import (
    EstimateResult,
    FailureReason,
    ReferenceObservation,
    confidence_from_inliers,
)
from services.estimators.correspondences import (
    StackedMatches,
    pose_sampson_errors_px,
    stack_matches,
)
from services.estimators.options import EstimatorOptions
from services.estimators.position_conditioning import reference_layout, reference_spread_deg
from services.estimators.ransac import Deadline, DeadlinePassedError
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d
from services.types import BoolArray

logger = logging.getLogger(__name__)


class EstimationError(Exception):
    """Ends ``Estimator.solve`` with a failure (raised by ``Request.fail``)."""

    def __init__(self, reason: FailureReason) -> None:
        super().__init__(reason.value)
        self.reason = reason


@dataclass
class Request:
    """One ``estimate`` call: its inputs, its deadline, and the stats gathered so far (they go
    into the result, a failure's too)."""

    query_camera: Camera
    references: list[ReferenceObservation]
    options: EstimatorOptions
    deadline: Deadline
    stats: dict[str, float] = field(default_factory=dict)

    @cached_property
    def stacked(self) -> StackedMatches:
        """The matches of all references, stacked on first use."""
        return stack_matches(self.query_camera, self.references)

    def fail(self, reason: FailureReason) -> NoReturn:
        raise EstimationError(reason)

    def fail_if_expired(self) -> None:
        if self.deadline.expired():
            self.fail(FailureReason.TIME_BUDGET_EXCEEDED)


@dataclass(frozen=True)
class Solution:
    """A method's pose, and its (N,) inliers over the stacked matches (Sampson error within
    ``max_error_px``) when the method has them already."""

    pose: Rigid3d
    inliers: BoolArray | None = None


def precheck(
    references: list[ReferenceObservation], min_matches: int, min_pairs: int = 2
) -> FailureReason | None:
    """Common input checks: at least ``min_pairs`` references with ``min_matches`` matches
    (else too_few_matches), and their centres not all coincident (else degenerate_geometry)."""
    if not references:
        return FailureReason.NO_REFERENCES
    usable = [ref for ref in references if ref.num_matches >= min_matches]
    if len(usable) < min_pairs:
        return FailureReason.TOO_FEW_MATCHES
    if min_pairs >= 2:
        centers = np.stack([ref.cam_from_world.center for ref in usable])
        scale = max(float(np.abs(centers).max()), 1.0)
        if float(np.ptp(centers, axis=0).max()) < 1e-6 * scale:
            return FailureReason.DEGENERATE_GEOMETRY
    return None


def missing_depth(references: list[ReferenceObservation]) -> FailureReason | None:
    """``missing_depth`` when there are references but the query has no depth map or none of
    them has one; None otherwise."""
    if references and (
        all(ref.query_depth is None for ref in references)
        or all(ref.reference_depth is None for ref in references)
    ):
        return FailureReason.MISSING_DEPTH
    return None


def finish(
    cam_from_world: Rigid3d,
    masks: list[BoolArray],
    references: list[ReferenceObservation],
    options: EstimatorOptions,
    stats: dict[str, float],
) -> EstimateResult:
    """Assemble the result: stats, confidence, and a ``no_consensus`` failure when the pose is
    not finite or supported by too few inliers / references."""
    num_inliers = int(sum(int(m.sum()) for m in masks))
    refs_with_inliers = sum(int(m.sum() >= 3) for m in masks)
    total = sum(ref.num_matches for ref in references)
    stats = {
        **stats,
        "num_matches": float(total),
        "num_inliers": float(num_inliers),
        "inlier_ratio": num_inliers / max(total, 1),
        "references_with_inliers": float(refs_with_inliers),
    }
    finite = np.all(np.isfinite(cam_from_world.rotation)) and np.all(
        np.isfinite(cam_from_world.translation)
    )
    acceptance = options.verification
    if (
        not finite
        or num_inliers < acceptance.min_inliers
        or refs_with_inliers < acceptance.min_references
    ):
        return EstimateResult(None, masks, 0.0, stats, FailureReason.NO_CONSENSUS)
    confidence = confidence_from_inliers(num_inliers, refs_with_inliers)
    return EstimateResult(cam_from_world, masks, confidence, stats, None)


class Estimator(ABC):
    """A pose estimator (``base.PoseEstimator``): ``check``, then ``solve``, then ``result``;
    a linear system found singular on the way is a ``degenerate_geometry`` failure, the
    deadline passing inside a long pass (``Deadline.check``) a ``time_budget_exceeded`` one.

    Attributes:
        name: the API name.
        needs_depth: the method needs depth for the query and the references.
        min_matches: ``precheck`` asks for two references with at least this many matches.
        position_from_baselines: the method gets the query's position from the references'
            baselines through epipolar constraints alone (E5+1, essential matrices), so its
            answer is checked for an unobservable position (``position_conditioning``).
    """

    name: str
    needs_depth: bool = False
    min_matches: int = 5
    position_from_baselines: bool = False

    def check(self, references: list[ReferenceObservation]) -> FailureReason | None:
        """Why the input cannot be solved, before any work; None when it can."""
        return precheck(references, self.min_matches)

    @abstractmethod
    def solve(self, request: Request) -> Solution:
        """The method: the query pose, or ``request.fail(reason)``."""

    def estimate(
        self,
        query_camera: Camera,
        references: list[ReferenceObservation],
        options: EstimatorOptions,
    ) -> EstimateResult:
        request = Request(query_camera, references, options, Deadline(options.time_budget_s))
        reason = missing_depth(references) if self.needs_depth else None
        reason = reason or self.check(references)
        if reason is not None:
            return EstimateResult.failure(reason, references)
        try:
            return self.result(request, self.solve(request))
        except EstimationError as failed:
            return EstimateResult.failure(failed.reason, references, request.stats)
        except DeadlinePassedError:  # inside a long pass: its pose would come too late
            return EstimateResult.failure(
                FailureReason.TIME_BUDGET_EXCEEDED, references, request.stats
            )
        except np.linalg.LinAlgError:  # a singular system the method's own checks let through
            logger.warning("%s: singular linear system", self.name, exc_info=True)
            return EstimateResult.failure(
                FailureReason.DEGENERATE_GEOMETRY, references, request.stats
            )

    def result(self, request: Request, solution: Solution) -> EstimateResult:
        """The answer: inliers within ``max_error_px`` Sampson error of the pose over the
        stacked matches, ``stats["score"]`` their count unless the method set it, and
        ``finish``."""
        options, references, pose = request.options, request.references, solution.pose
        inliers = solution.inliers
        if inliers is None:
            errors = pose_sampson_errors_px(
                request.stacked, pose.rotation[None], pose.center[None], deadline=request.deadline
            )[0]
            inliers = errors < options.ransac.max_error_px
        request.stats.setdefault("score", float(inliers.sum()))
        masks = request.stacked.split(inliers)
        if self.position_from_baselines:
            self.check_position(request, pose, masks)
        return finish(pose, masks, references, options, request.stats)

    @staticmethod
    def check_position(request: Request, pose: Rigid3d, masks: list[BoolArray]) -> None:
        """Fails the request with ``degenerate_geometry`` when the query's position is not
        observable from the references' baselines: the references with inliers lie on a line
        they look along (forward motion), or, seen from the query, they spread less than
        ``min_reference_spread_deg`` around some direction (the query on the line of their
        centres; a reference set far narrower than its distance). Records
        ``reference_spread_deg`` and ``reference_collinearity`` in the stats."""
        stacked = request.stacked
        weights = np.array([float(mask.sum()) for mask in masks])
        spread = reference_spread_deg(pose.center, stacked.C_ref, weights)
        layout = reference_layout(stacked.C_ref, stacked.R_ref[:, 2, :], weights)
        request.stats["reference_spread_deg"] = spread
        request.stats["reference_collinearity"] = layout.collinearity
        if layout.forward_motion or spread < request.options.verification.min_reference_spread_deg:
            request.fail(FailureReason.DEGENERATE_GEOMETRY)
