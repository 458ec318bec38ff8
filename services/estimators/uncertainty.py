"""Uncertainty of a localized pose in metres and degrees, and the confidence cap it implies.

Whatever the estimator, the pose's inlier tracks are triangulated from the references alone
(the 3D verification of ``services.estimators.verification``); the verified points and their query
keypoints give the first-order covariance of the pose at the answer
(``services.geometry.pose_covariance``: Gauss–Newton, pixel noise estimated from the
residuals, the focal length a free parameter when it was estimated, so its uncertainty widens
the pose's). Reported as root-mean-square errors: ``position_m = sqrt(trace Σ_C)`` and
``rotation_deg = sqrt(trace Σ_θ)``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

import numpy as np

from services.estimators.base import EstimateResult, ReferenceObservation
from services.estimators.options import EstimatorOptions, UncertaintyOptions
from services.estimators.ransac import Deadline
from services.estimators.verification import check_structure
from services.geometry.camera import Camera
from services.geometry.pose_covariance import pose_covariance
from services.geometry.projection import normalized_from_pixels


@dataclass(frozen=True)
class PoseUncertainty:
    """Attributes:
    position_m: RMS camera-centre error predicted, map units (metres on a metric map).
    rotation_deg: RMS rotation-angle error predicted, degrees.
    num_points: verified 3D points it rests on.
    sigma_px: the pixel noise estimated from their residuals.
    """

    position_m: float
    rotation_deg: float
    num_points: int
    sigma_px: float


def pose_uncertainty(
    result: EstimateResult,
    query_camera: Camera,
    references: list[ReferenceObservation],
    options: EstimatorOptions,
    focal_estimated: bool,
    deadline: Deadline | None = None,
) -> PoseUncertainty | None:
    """The uncertainty of ``result``'s pose; None without a pose or with fewer than
    ``options.uncertainty.min_points`` verified points.

    Raises:
        DeadlinePassedError: ``deadline`` passed during the structure check.
    """
    pose = result.cam_from_world
    if pose is None or result.num_inliers == 0:
        return None
    checked = check_structure(
        query_camera, pose, references, result.inliers, options.ransac.max_error_px, deadline
    )
    if checked is None:
        return None
    check, track_xy = checked
    verified = check.point_verified
    if int(verified.sum()) < options.uncertainty.min_points:
        return None
    focal = float(np.mean(query_camera.focal_lengths))
    # undistorted pixels relative to the principal point, at the mean focal length
    centered = normalized_from_pixels(query_camera, track_xy[verified]) * focal
    covariance = pose_covariance(
        pose, check.points[verified], centered, focal, with_focal=focal_estimated
    )
    if covariance is None:
        return None
    return PoseUncertainty(
        covariance.position_rms,
        covariance.rotation_rms_deg,
        covariance.num_points,
        covariance.sigma_px,
    )


def capped_confidence(
    confidence: float,
    uncertainty: PoseUncertainty | None,
    options: UncertaintyOptions,
    focal_estimated: bool,
    stats: Mapping[str, float] | None = None,
) -> float:
    """``confidence``, capped at ``options.capped_confidence`` when the 3σ uncertainty exceeds
    the limits, when the focal length was estimated and no uncertainty could be computed, or
    when ``auto``'s other verified pose is turned more than ``max_disagreement_deg`` from the
    answer (``auto_other_rotation_deg`` in ``stats``: on redkitchen, a third of the answers
    whose two poses from the same matches were turned that far apart were right)."""
    stats = stats or {}
    disagree = stats.get("auto_other_rotation_deg", 0.0) > options.max_disagreement_deg
    if disagree or (uncertainty is None and focal_estimated):
        return min(confidence, options.capped_confidence)
    if uncertainty is not None and (
        3.0 * uncertainty.position_m > options.max_position_3sigma_m
        or 3.0 * uncertainty.rotation_deg > options.max_rotation_3sigma_deg
    ):
        return min(confidence, options.capped_confidence)
    return confidence


def uncertainty_stats(uncertainty: PoseUncertainty | None) -> dict[str, float]:
    """Result stats for confidence models: ``position_sigma_m``, ``rotation_sigma_deg``,
    ``uncertainty_points``, ``uncertainty_sigma_px`` (empty without an uncertainty)."""
    if uncertainty is None:
        return {}
    return {
        "position_sigma_m": uncertainty.position_m,
        "rotation_sigma_deg": uncertainty.rotation_deg,
        "uncertainty_points": float(uncertainty.num_points),
        "uncertainty_sigma_px": uncertainty.sigma_px,
    }


def with_uncertainty(
    result: EstimateResult,
    query_camera: Camera,
    references: list[ReferenceObservation],
    options: EstimatorOptions,
    focal_estimated: bool,
    score: Callable[[EstimateResult], EstimateResult] | None = None,
    deadline: Deadline | None = None,
) -> tuple[EstimateResult, PoseUncertainty | None]:
    """``result`` with the uncertainty in its stats, scored by ``score`` (which may read
    them: the calibrated confidence, ``services.confidence``) and its confidence then capped
    by the uncertainty; and the uncertainty (None without a pose or without enough verified
    points).

    Raises:
        DeadlinePassedError: ``deadline`` passed during the structure check.
    """
    if result.cam_from_world is None:
        return result, None
    uncertainty = pose_uncertainty(
        result, query_camera, references, options, focal_estimated, deadline
    )
    result = replace(result, stats={**result.stats, **uncertainty_stats(uncertainty)})
    if score is not None:
        result = score(result)
    confidence = capped_confidence(
        result.confidence, uncertainty, options.uncertainty, focal_estimated, result.stats
    )
    return replace(result, confidence=confidence), uncertainty
