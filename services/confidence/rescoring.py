"""The confidence of a verified pose: geometry of its inliers added to the result's stats, then
the calibrated model's probability that the pose is right (``services.confidence.model``)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from services.confidence.model import ConfidenceModel
from services.estimators.base import EstimateResult, ReferenceObservation
from services.estimators.correspondences import pose_sampson_errors_px, stack_matches
from services.estimators.options import EstimatorOptions
from services.estimators.ransac import Deadline
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d
from services.types import BoolArray, FloatArray

# the query image is cut into GRID × GRID cells for the inliers' spread
GRID = 8
MAX_RADIAL_RATIO = 5.0


def inlier_area_fraction(query_xy: FloatArray, width: int, height: int, grid: int = GRID) -> float:
    """Fraction of the ``grid`` × ``grid`` cells of a ``width`` × ``height`` image that hold at
    least one of the (K, 2) pixels (COLMAP convention; pixels outside count in the edge cell)."""
    if query_xy.shape[0] == 0:
        return 0.0
    col = np.clip((query_xy[:, 0] / width * grid).astype(np.int64), 0, grid - 1)
    row = np.clip((query_xy[:, 1] / height * grid).astype(np.int64), 0, grid - 1)
    return float(np.unique(row * grid + col).size / (grid * grid))


def inlier_residuals_px(
    camera: Camera,
    references: list[ReferenceObservation],
    inliers: list[BoolArray],
    cam_from_world: Rigid3d,
    deadline: Deadline | None = None,
) -> FloatArray:
    """(K,) Sampson errors (≈ pixels) of the K inliers under the pose, in stacked order
    (``deadline`` polled between chunks: ``pose_sampson_errors_px``)."""
    stacked = stack_matches(camera, references)
    subset = np.flatnonzero(np.concatenate(inliers)) if inliers else np.zeros(0, np.int64)
    if subset.size == 0:
        return np.zeros(0)
    errors: FloatArray = pose_sampson_errors_px(
        stacked, cam_from_world.rotation[None], cam_from_world.center[None], subset, deadline
    )[0]
    return errors


def radial_residual_ratio(errors: FloatArray, query_xy: FloatArray, camera: Camera) -> float:
    """Median error of the (K,) inliers farther from the principal point than their median
    distance over that of the nearer ones, at most ``MAX_RADIAL_RATIO`` (1 without inliers).
    A wrong focal length leaves errors that grow with the distance from the principal point."""
    if errors.size < 2:
        return 1.0
    radius = np.linalg.norm(query_xy - np.asarray(camera.principal_point), axis=1)
    outer = radius > np.median(radius)
    if outer.all() or not outer.any():
        return 1.0
    inner_median = max(float(np.median(errors[~outer])), 1e-6)
    return min(float(np.median(errors[outer])) / inner_median, MAX_RADIAL_RATIO)


def inlier_geometry(
    camera: Camera,
    references: list[ReferenceObservation],
    inliers: list[BoolArray],
    cam_from_world: Rigid3d,
    max_error_px: float,
    deadline: Deadline | None = None,
) -> dict[str, float]:
    """Stats of a pose and its inlier masks: ``inlier_area_fraction``,
    ``inlier_residual_ratio`` (median inlier error over the inlier threshold),
    ``inlier_tight_fraction`` (inliers within a quarter of the threshold) and
    ``radial_residual_ratio``."""
    used = [ref.query_xy[mask] for ref, mask in zip(references, inliers, strict=True)]
    query_xy = np.concatenate(used) if used else np.zeros((0, 2))
    errors = inlier_residuals_px(camera, references, inliers, cam_from_world, deadline)
    return {
        "inlier_area_fraction": inlier_area_fraction(query_xy, camera.width, camera.height),
        "inlier_residual_ratio": float(np.median(errors)) / max_error_px if errors.size else 0.0,
        "inlier_tight_fraction": float(np.mean(errors < max_error_px / 4.0))
        if errors.size
        else 0.0,
        "radial_residual_ratio": radial_residual_ratio(errors, query_xy, camera),
    }


def rescore(
    result: EstimateResult,
    camera: Camera,
    references: list[ReferenceObservation],
    options: EstimatorOptions,
    estimator: str,
    model: ConfidenceModel,
    deadline: Deadline | None = None,
) -> EstimateResult:
    """``result`` with the geometry of its inliers in its stats and the model's confidence;
    a result without a pose unchanged.

    Raises:
        DeadlinePassedError: ``deadline`` passed while the inliers' errors were measured.
    """
    pose = result.cam_from_world
    if pose is None:
        return result
    geometry = inlier_geometry(
        camera, references, result.inliers, pose, options.ransac.max_error_px, deadline
    )
    stats = {**result.stats, **geometry}
    return replace(result, stats=stats, confidence=model.confidence(stats, estimator))
