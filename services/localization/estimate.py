"""The estimate stage of a localization: the query camera (the request's, or estimated from the
matches), the estimator's pose, its 3D verification, and its uncertainty with the confidence
cap it implies."""

from __future__ import annotations

from dataclasses import dataclass, replace

from services.confidence.model import ConfidenceModel
from services.confidence.rescoring import rescore
from services.estimators.base import (
    EstimateResult,
    FailureReason,
    PoseEstimator,
    ReferenceObservation,
)
from services.estimators.estimator import missing_depth
from services.estimators.focal import estimate_focal
from services.estimators.options import EstimatorOptions
from services.estimators.ransac import Deadline, DeadlinePassedError
from services.estimators.uncertainty import PoseUncertainty, with_uncertainty
from services.estimators.verification import VERIFIED_POINTS, verify_pose
from services.geometry.camera import Camera
from services.localization.undistort import undistort_matches


@dataclass(frozen=True)
class PoseAnswer:
    """Attributes:
    result: the verified estimate, confidence capped, focal and uncertainty stats included.
    camera: the query camera used; None when the focal length was not determined.
    uncertainty: of the pose, when there is one and enough verified points.
    """

    result: EstimateResult
    camera: Camera | None
    uncertainty: PoseUncertainty | None


def answer_pose(
    estimator: PoseEstimator,
    camera: Camera,
    focal_estimated: bool,
    references: list[ReferenceObservation],
    options: EstimatorOptions,
    deadline: Deadline,
    confidence_model: ConfidenceModel,
) -> PoseAnswer:
    """Estimate and verify the query pose with ``camera``, or, when ``focal_estimated``, with
    the camera estimated from the matches (``camera`` gives only the image size then); a
    depth estimator without depth fails as ``missing_depth`` before any focal estimation. The
    confidence is ``confidence_model``'s (of the estimator ``auto`` chose, for ``auto``) over
    the result's stats, the uncertainty's included, then capped by the uncertainty. Distorted
    cameras are undistorted first (``undistort_matches``); the answer's masks are over the
    matches as given and its camera is the one given (or estimated).

    ``deadline`` is checked between the steps and inside their passes over the inliers: a pose
    found or verified after it has passed is a ``time_budget_exceeded`` answer, not verified
    or scored further (with 100 references of 1000 matches each, verification, uncertainty
    and rescoring take about half a second)."""
    given_camera, given_references = camera, references
    # distorted cameras (any COLMAP model) become pinholes with undistorted keypoints
    undistorted = undistort_matches(camera, references)
    camera, references = undistorted.camera, undistorted.references
    focal_stats: dict[str, float] = {}
    if focal_estimated and not (estimator.needs_depth and missing_depth(references)):
        focal = estimate_focal(camera.width, camera.height, references, options, deadline)
        if focal.camera is None:
            reason = focal.failure_reason or FailureReason.FOCAL_UNOBSERVABLE
            failure = EstimateResult.failure(reason, given_references, focal.stats)
            return PoseAnswer(failure, None, None)
        camera, focal_stats = focal.camera, focal.stats
        # the estimator gets what the focal estimation left of the budget
        left = deadline.remaining_s()
        if left != float("inf"):
            own = options.time_budget_s
            options = replace(
                options, time_budget_s=max(0.0, left if own is None else min(own, left))
            )
    answer_camera = camera if focal_estimated else given_camera

    def spent(result: EstimateResult) -> EstimateResult | None:
        """The ``time_budget_exceeded`` failure once the deadline has passed on a pose."""
        if result.cam_from_world is None or not deadline.expired():
            return None
        stats = {**result.stats, **focal_stats}
        return EstimateResult.failure(FailureReason.TIME_BUDGET_EXCEEDED, references, stats)

    estimated = estimator.estimate(camera, references, options)
    late = spent(estimated)
    # a pose verified already (``auto`` verifies each pose it compares) is not checked again
    checked = late is not None or VERIFIED_POINTS in estimated.stats
    verified = (
        estimated if checked else verify_pose(estimated, camera, references, options, deadline)
    )
    late = late or spent(verified)
    if late is not None:
        return PoseAnswer(undistorted.result_as_given(late), answer_camera, None)
    name = verified.estimator_used or estimator.name

    def score(result: EstimateResult) -> EstimateResult:
        return spent(result) or rescore(
            result, camera, references, options, name, confidence_model, deadline
        )

    try:
        result, uncertainty = with_uncertainty(
            verified, camera, references, options, focal_estimated, score, deadline
        )
    except DeadlinePassedError:
        late = EstimateResult.failure(
            FailureReason.TIME_BUDGET_EXCEEDED, references, {**verified.stats, **focal_stats}
        )
        return PoseAnswer(undistorted.result_as_given(late), answer_camera, None)
    if result.cam_from_world is None:
        uncertainty = None
    result = undistorted.result_as_given(replace(result, stats={**result.stats, **focal_stats}))
    return PoseAnswer(result, answer_camera, uncertainty)
