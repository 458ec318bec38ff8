"""Uncertainty of a localized pose in metres and degrees, and the confidence cap it implies.

Whatever the estimator, the pose's inlier tracks are triangulated from the references alone
(the 3D verification of ``services.estimators.verification``); the verified points and their query
keypoints give the first-order covariance of the pose at the answer
(``services.geometry.pose_covariance``: Gauss–Newton, pixel noise estimated from the
residuals, the focal length a free parameter when it was estimated, so its uncertainty widens
the pose's). Each point carries the uncertainty of its own triangulation from the references
(their observations at the same pixel noise): a query beyond the map's end, resting on points
that references a metre apart saw tens of metres away, is placed along its view no better than
those points are. The references' poses carry the spread of ``UncertaintyOptions``
(``reference_position_sigma_m``, ``reference_rotation_sigma_deg``): a reference's pose
error moves every point it saw the same way. Reported as root-mean-square errors:
``position_m = sqrt(trace Σ_C)`` and ``rotation_deg = sqrt(trace Σ_θ)``.

The confidence model reads the covariance given the points (the points exact:
``position_sigma_m``, ``rotation_sigma_deg`` in the stats), the one it was fitted on; the
uncertainty reported and the cap use the one with the points' own uncertainty
(``structure_position_sigma_m``, ``structure_rotation_sigma_deg``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

import numpy as np

from services.estimators.base import EstimateResult, ReferenceObservation
from services.estimators.options import EstimatorOptions, UncertaintyOptions
from services.estimators.ransac import Deadline
from services.estimators.verification import CheckedTracks, structure_of
from services.geometry.camera import Camera
from services.geometry.pose_covariance import (
    ReferenceViews,
    RigObservations,
    pose_covariance,
    rig_pose_covariance,
)
from services.geometry.projection import normalized_from_pixels
from services.geometry.rigid import Rigid3d
from services.types import IntArray


@dataclass(frozen=True)
class PoseUncertainty:
    """Attributes:
    position_m: RMS camera-centre error predicted, map units (metres on a metric map), the
        points' own uncertainty included.
    rotation_deg: RMS rotation-angle error predicted, degrees, the same.
    num_points: verified 3D points it rests on.
    sigma_px: the pixel noise estimated from their residuals.
    given_points_position_m: the RMS camera-centre error were the points exact.
    given_points_rotation_deg: the same for the rotation.
    """

    position_m: float
    rotation_deg: float
    num_points: int
    sigma_px: float
    given_points_position_m: float
    given_points_rotation_deg: float


def pose_uncertainty(
    result: EstimateResult,
    query_camera: Camera,
    references: list[ReferenceObservation],
    options: EstimatorOptions,
    focal_estimated: bool,
    deadline: Deadline | None = None,
) -> PoseUncertainty | None:
    """The uncertainty of ``result``'s pose; None without a pose, with fewer than
    ``options.uncertainty.min_points`` verified points or when they leave it undetermined.

    Raises:
        DeadlinePassedError: ``deadline`` passed during the structure check.
    """
    pose = result.cam_from_world
    if pose is None or result.num_inliers == 0:
        return None
    checked = structure_of(result, query_camera, references, options.ransac.max_error_px, deadline)
    if checked is None:
        return None
    check = checked.check
    verified = check.point_verified
    if int(verified.sum()) < options.uncertainty.min_points:
        return None
    focal = float(np.mean(query_camera.focal_lengths))
    # undistorted pixels relative to the principal point, at the mean focal length
    centered = normalized_from_pixels(query_camera, checked.track_xy[verified]) * focal
    points = check.points[verified]
    given_points = pose_covariance(pose, points, centered, focal, with_focal=focal_estimated)
    if given_points is None:
        return None
    with_points = pose_covariance(
        pose,
        points,
        centered,
        focal,
        with_focal=focal_estimated,
        references=_reference_views(checked, references, options.uncertainty),
    )
    if with_points is None:  # the points' own freedom leaves the pose undetermined
        return None
    return PoseUncertainty(
        with_points.position_rms,
        with_points.rotation_rms_deg,
        given_points.num_points,
        given_points.sigma_px,
        given_points.position_rms,
        given_points.rotation_rms_deg,
    )


def rig_pose_uncertainty(
    poses: list[Rigid3d],
    cameras: list[Camera],
    checks: list[CheckedTracks | None],
    options: UncertaintyOptions,
) -> PoseUncertainty | None:
    """The uncertainty of the first frame's pose when the frames move together (a rig whose
    relative poses are known, ``services.estimators.rig_pose``), from each frame's inlier
    tracks checked in 3D at its pose (``checks``, None for a frame without); a point that
    several frames verified (the same keypoint of a reference) is one point, whose reference
    observations count once (``rig_pose_covariance``). None with fewer than
    ``options.min_points`` verified points over all frames or when they leave the pose
    undetermined."""
    verified = sum(int(c.check.point_verified.sum()) for c in checks if c is not None)
    if verified < options.min_points:
        return None
    observed, views = _rig_observations(poses, cameras, checks, options)
    given_points = rig_pose_covariance(observed)
    with_points = rig_pose_covariance(observed, views)
    if given_points is None or with_points is None:
        return None
    return PoseUncertainty(
        with_points.position_rms,
        with_points.rotation_rms_deg,
        len(observed.points3d),
        given_points.sigma_px,
        given_points.position_rms,
        given_points.rotation_rms_deg,
    )


def _rig_observations(
    poses: list[Rigid3d],
    cameras: list[Camera],
    checks: list[CheckedTracks | None],
    options: UncertaintyOptions,
) -> tuple[RigObservations, ReferenceViews]:
    """The frames' verified points merged: two frames' points that rest on the same reference
    keypoint (its image and exact pixel) are one point, placed where the first frame
    triangulated it; each reference observation once; each reference (by image id) once."""
    image_ids: dict[str, int] = {}
    reference_poses: list[ReferenceObservation] = []
    rows_key, rows_node, xy, view_of, positions = [], [], [], [], []
    offset = 0
    for v, (camera, checked) in enumerate(zip(cameras, checks, strict=True)):
        if checked is None:
            continue
        refs, masks = checked.inputs[2], checked.inputs[3]
        check = checked.check
        verified = np.flatnonzero(check.point_verified)
        node_of = np.full(len(check.point_verified), -1, np.int64)
        node_of[verified] = offset + np.arange(len(verified))
        offset += len(verified)
        focal = float(np.mean(camera.focal_lengths))
        xy.append(normalized_from_pixels(camera, checked.track_xy[verified]) * focal)
        view_of.append(np.full(len(verified), v, np.int64))
        positions.append(check.points[verified])
        for ref in refs:
            if ref.image_id not in image_ids:
                image_ids[ref.image_id] = len(image_ids)
                reference_poses.append(ref)
        rows = np.flatnonzero(check.correspondence_verified)
        global_ref = np.array([image_ids[ref.image_id] for ref in refs], np.int64)
        used = [i for i, mask in enumerate(masks) if mask.any()]
        reference_xy = np.concatenate([refs[i].reference_xy[masks[i]] for i in used])
        rows_key.append(
            np.column_stack([global_ref[checked.reference_of[rows]], reference_xy[rows]])
        )
        rows_node.append(node_of[checked.track_of[rows]])
    keys, key_of = np.unique(np.concatenate(rows_key), axis=0, return_inverse=True)
    row_node = np.concatenate(rows_node)
    point_of_node = _shared_components(row_node, key_of.reshape(-1), offset, len(keys))
    # each point where the first of its nodes placed it
    first_node = np.unique(point_of_node, return_index=True)[1]
    points3d = np.concatenate(positions)[first_node]
    observed = RigObservations(
        poses,
        np.array([float(np.mean(c.focal_lengths)) for c in cameras]),
        np.concatenate(view_of),
        point_of_node,
        np.concatenate(xy),
        points3d,
    )
    # one observation per reference keypoint: its point and its reference
    views = ReferenceViews(
        point_of=point_of_node[row_node[np.unique(key_of.reshape(-1), return_index=True)[1]]],
        camera_of=keys[:, 0].astype(np.int64),
        rotations=np.stack([r.cam_from_world.rotation for r in reference_poses]),
        translations=np.stack([r.cam_from_world.translation for r in reference_poses]),
        focals=np.array([float(np.mean(r.camera.focal_lengths)) for r in reference_poses]),
        rotation_sigma_rad=math.radians(options.reference_rotation_sigma_deg),
        position_sigma=options.reference_position_sigma_m,
    )
    return observed, views


def _shared_components(row_node: IntArray, row_key: IntArray, nodes: int, keys: int) -> IntArray:
    """(nodes,) the point of each node: nodes linked through a shared key are one point (each
    takes the least node of its component, spread through the keys until nothing changes),
    numbered 0… in order of appearance."""
    label = np.arange(nodes)
    while True:
        least = np.full(keys, nodes)
        np.minimum.at(least, row_key, label[row_node])
        spread = label.copy()
        np.minimum.at(spread, row_node, least[row_key])
        if np.array_equal(spread, label):
            break
        label = spread
    return np.unique(label, return_inverse=True)[1].reshape(-1)


def _reference_views(
    checked: CheckedTracks, references: list[ReferenceObservation], options: UncertaintyOptions
) -> ReferenceViews:
    """The agreeing reference observations of each verified point, indexed in the order of
    the verified points, with the references' pose spread of ``options``."""
    check = checked.check
    verified = np.flatnonzero(check.point_verified)
    index_of = np.full(len(check.point_verified), -1, np.int64)
    index_of[verified] = np.arange(len(verified))
    rows = np.flatnonzero(check.correspondence_verified)
    return ReferenceViews(
        point_of=index_of[checked.track_of[rows]],
        camera_of=checked.reference_of[rows],
        rotations=np.stack([r.cam_from_world.rotation for r in references]),
        translations=np.stack([r.cam_from_world.translation for r in references]),
        focals=np.array([float(np.mean(r.camera.focal_lengths)) for r in references]),
        rotation_sigma_rad=math.radians(options.reference_rotation_sigma_deg),
        position_sigma=options.reference_position_sigma_m,
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
    whose two poses from the same matches were turned that far apart were right); and never
    above the probability the uncertainty leaves for the confidence's target
    (``within_target_probability``)."""
    stats = stats or {}
    capped = (
        stats.get("auto_other_rotation_deg", 0.0) > options.max_disagreement_deg
        or (uncertainty is None and focal_estimated)
        or (
            uncertainty is not None
            and (
                3.0 * uncertainty.position_m > options.max_position_3sigma_m
                or 3.0 * uncertainty.rotation_deg > options.max_rotation_3sigma_deg
            )
        )
    )
    if capped:
        confidence = min(confidence, options.capped_confidence)
    if uncertainty is not None:
        confidence = min(confidence, within_target_probability(uncertainty, options))
    return confidence


def within_target_probability(uncertainty: PoseUncertainty, options: UncertaintyOptions) -> float:
    """The probability that the pose lies within ``options.target_position_m`` and
    ``options.target_rotation_deg`` of the truth, were its errors Gaussian with the
    uncertainty's RMS values spread evenly over three axes: the product of the two chi-square
    (three degrees of freedom) probabilities."""
    return _within_rms(options.target_position_m, uncertainty.position_m) * _within_rms(
        options.target_rotation_deg, uncertainty.rotation_deg
    )


def _within_rms(radius: float, rms: float) -> float:
    """P(|e| ≤ radius) for a 3D isotropic Gaussian error whose RMS length is ``rms``: the
    chi-square CDF with three degrees of freedom at ``x = 3 radius² / rms²``,
    ``erf(√(x/2)) − √(2x/π) e^(−x/2)``."""
    if rms <= 0.0:
        return 1.0
    x = 3.0 * radius * radius / (rms * rms)
    return math.erf(math.sqrt(x / 2.0)) - math.sqrt(2.0 * x / math.pi) * math.exp(-x / 2.0)


def uncertainty_stats(uncertainty: PoseUncertainty | None) -> dict[str, float]:
    """Result stats for confidence models: ``position_sigma_m``, ``rotation_sigma_deg`` (the
    points taken as exact), ``structure_position_sigma_m``, ``structure_rotation_sigma_deg``
    (their own uncertainty included: the answer's), ``uncertainty_points``,
    ``uncertainty_sigma_px`` (empty without an uncertainty)."""
    if uncertainty is None:
        return {}
    return {
        "position_sigma_m": uncertainty.given_points_position_m,
        "rotation_sigma_deg": uncertainty.given_points_rotation_deg,
        "structure_position_sigma_m": uncertainty.position_m,
        "structure_rotation_sigma_deg": uncertainty.rotation_deg,
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
