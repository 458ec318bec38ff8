"""Focal length of a query sent without intrinsics, from its matches to posed references.

The references' observations of each query keypoint are triangulated on the fly (the tracks
and RANSAC triangulation of local triangulation, ``services.estimators.tracks``), which turns
the matches into 2D–3D correspondences; pycolmap's absolute pose estimator with an unknown
focal length (LO-RANSAC, then refinement of pose and focal) fits them. The camera is a
SIMPLE_PINHOLE with its principal point at the image centre and no distortion.

The focal length counts as determined only when the data pin it down: enough 2D–3D inliers,
a small standard deviation from the pose-and-focal covariance
(``services.geometry.pose_covariance``), two random halves of the inliers agreeing, and a
plausible field of view. Otherwise the answer is ``focal_unobservable``: a pose computed with
a focal length the data do not determine is a confident wrong answer waiting to happen.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import pycolmap

from services.estimators.base import FailureReason, ReferenceObservation
from services.estimators.correspondences import StackedMatches, stack_matches
from services.estimators.options import EstimatorOptions, FocalOptions
from services.estimators.ransac import Deadline
from services.estimators.tracks import Tracks, build_tracks, triangulate_tracks
from services.geometry.camera import Camera, default_camera
from services.geometry.pose_covariance import pose_covariance
from services.geometry.rigid import Rigid3d
from services.types import BoolArray, FloatArray, IntArray

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class FocalEstimate:
    """Attributes:
    camera: the estimated SIMPLE_PINHOLE camera, or None when the focal is unobservable.
    failure_reason: set exactly when ``camera`` is None.
    stats: ``focal_px``, ``focal_relative_sigma``, ``focal_points`` (2D–3D inliers),
        ``focal_relative_disagreement`` (between halves of the inliers), where reached.
    """

    camera: Camera | None
    failure_reason: FailureReason | None = None
    stats: dict[str, float] = field(default_factory=dict)


def _fit(
    xy: FloatArray,
    points3d: FloatArray,
    width: int,
    height: int,
    max_error_px: float,
    seed: int,
    max_trials: int,
) -> tuple[float, Rigid3d, BoolArray] | None:
    """pycolmap robust pose + focal; (focal, cam_from_world, inlier mask) or None."""
    guess = default_camera(width, height)
    camera = pycolmap.Camera(
        model="SIMPLE_PINHOLE", width=width, height=height, params=list(guess.params)
    )
    estimation = pycolmap.AbsolutePoseEstimationOptions()
    estimation.estimate_focal_length = True
    estimation.ransac.max_error = max_error_px
    estimation.ransac.random_seed = seed
    estimation.ransac.max_num_trials = max_trials
    refinement = pycolmap.AbsolutePoseRefinementOptions()
    refinement.refine_focal_length = True
    out = pycolmap.estimate_and_refine_absolute_pose(
        np.ascontiguousarray(xy), np.ascontiguousarray(points3d), camera, estimation, refinement
    )
    if out is None:
        return None
    focal = float(camera.params[0])  # pycolmap writes the estimate into the camera
    pose = out["cam_from_world"]
    rigid = Rigid3d(np.asarray(pose.rotation.matrix()), np.asarray(pose.translation))
    mask = np.asarray(out["inlier_mask"], dtype=bool).reshape(-1)
    if not np.isfinite(focal) or focal <= 0 or not np.all(np.isfinite(rigid.matrix)):
        return None
    return focal, rigid, mask


def _refit_focal(
    xy: FloatArray, points3d: FloatArray, width: int, height: int, focal: float, pose: Rigid3d
) -> float | None:
    """Pose and focal refined from ``focal``/``pose`` on a subset (pycolmap)."""
    camera = pycolmap.Camera(
        model="SIMPLE_PINHOLE", width=width, height=height, params=[focal, width / 2, height / 2]
    )
    refinement = pycolmap.AbsolutePoseRefinementOptions()
    refinement.refine_focal_length = True
    out = pycolmap.refine_absolute_pose(
        pycolmap.Rigid3d(pycolmap.Rotation3d(pose.rotation), pose.translation),
        np.ascontiguousarray(xy),
        np.ascontiguousarray(points3d),
        np.ones(xy.shape[0], dtype=bool),
        camera,
        refinement,
    )
    refined = float(camera.params[0])
    return refined if out is not None and np.isfinite(refined) and refined > 0 else None


def _jackknife_sigma(
    stacked: StackedMatches,
    tracks: Tracks,
    rows: IntArray,
    width: int,
    height: int,
    focal: float,
    pose: Rigid3d,
    options: EstimatorOptions,
    deadline: Deadline,
) -> float | None:
    """Leave-one-reference-out standard deviation of the focal length, pixels: the inlier
    tracks ``rows`` are triangulated again without each reference and the focal refined on
    them. Errors shared by one reference's points (its pose, its lens) move the points
    together, which the per-point covariance cannot see; the jackknife does. None when the
    ``deadline`` passes before every reference was left out (one refit per reference: with
    many references this is the longest part of the focal estimation)."""
    num_views = tracks.match_index.shape[1]
    observed = tracks.subset(rows)
    refits = []
    for left_out in range(num_views):
        if deadline.expired():
            return None
        if not observed.observed[:, left_out].any():
            continue
        views = np.delete(np.arange(num_views), left_out)
        tri = triangulate_tracks(
            stacked, observed, options.triangulation.max_error_px, views, deadline=deadline
        )
        keep = np.flatnonzero(tri.valid)
        if keep.size < options.focal.min_points:
            continue
        xy = stacked.query_xy[observed.query_match[keep]]
        refit = _refit_focal(xy, tri.points[keep], width, height, focal, pose)
        if refit is not None:
            refits.append(refit)
    n = len(refits)
    if n < 3:
        return 0.0
    values = np.asarray(refits)
    return float(np.sqrt((n - 1) / n * np.sum((values - values.mean()) ** 2)))


def estimate_focal(
    width: int,
    height: int,
    references: list[ReferenceObservation],
    options: EstimatorOptions,
    deadline: Deadline,
) -> FocalEstimate:
    """The query camera of a ``width`` × ``height`` image from its matches (pixels in COLMAP
    convention), or ``focal_unobservable`` with the stats gathered so far; or
    ``time_budget_exceeded`` when the request's ``deadline`` passes first (it is checked
    between the steps and between the refits of the jackknife)."""
    focal_options: FocalOptions = options.focal
    stats: dict[str, float] = {}

    def unobservable() -> FocalEstimate:
        return FocalEstimate(None, FailureReason.FOCAL_UNOBSERVABLE, stats)

    def out_of_time() -> FocalEstimate:
        return FocalEstimate(None, FailureReason.TIME_BUDGET_EXCEEDED, stats)

    if deadline.expired():
        return out_of_time()

    guess = default_camera(width, height)
    stacked = stack_matches(guess, references)  # the query camera is not used below
    tracks = build_tracks(stacked, options.triangulation.track_merge_px).multi_view()
    if tracks.size < focal_options.min_points:
        return unobservable()
    if deadline.expired():
        return out_of_time()
    tri = triangulate_tracks(stacked, tracks, options.triangulation.max_error_px, deadline=deadline)
    if deadline.expired():
        return out_of_time()
    valid = np.flatnonzero(tri.valid)
    stats["focal_tracks"] = float(valid.size)
    if valid.size < focal_options.min_points:
        return unobservable()
    xy = stacked.query_xy[tracks.query_match[valid]]
    points3d = tri.points[valid]
    fit = _fit(
        xy,
        points3d,
        width,
        height,
        options.ransac.max_error_px,
        options.ransac.seed,
        min(options.ransac.max_iterations, 10_000),
    )
    if fit is None:
        return unobservable()
    if deadline.expired():
        return out_of_time()
    focal, pose, mask = fit
    stats["focal_px"] = focal
    stats["focal_points"] = float(mask.sum())
    if mask.sum() < focal_options.min_points:
        return unobservable()
    center = np.array([width / 2.0, height / 2.0])
    covariance = pose_covariance(pose, points3d[mask], xy[mask] - center, focal, with_focal=True)
    sigma = covariance.focal_sigma if covariance is not None else None
    if sigma is None:
        return unobservable()
    stats["focal_relative_sigma_points"] = sigma / focal
    jackknife = _jackknife_sigma(
        stacked, tracks, valid[mask], width, height, focal, pose, options, deadline
    )
    if jackknife is None or deadline.expired():
        return out_of_time()
    stats["focal_relative_sigma_references"] = jackknife / focal
    sigma = max(sigma, jackknife)
    stats["focal_relative_sigma"] = sigma / focal
    # two random halves of the inliers must agree on the focal length
    inlier_rows = np.flatnonzero(mask)
    halves = np.array_split(np.random.default_rng(options.ransac.seed).permutation(inlier_rows), 2)
    refits = [_refit_focal(xy[h], points3d[h], width, height, focal, pose) for h in halves]
    disagreement = (
        abs(refits[0] - refits[1]) / focal
        if refits[0] is not None and refits[1] is not None
        else float("inf")
    )
    stats["focal_relative_disagreement"] = disagreement
    fov = np.degrees(2.0 * np.arctan(max(width, height) / (2.0 * focal)))
    low, high = focal_options.field_of_view_deg
    if (
        sigma / focal > focal_options.max_relative_sigma
        or disagreement > focal_options.halves_sigmas * 2.0 * sigma / focal
        or not low <= fov <= high
    ):
        logger.info(
            "focal unobservable: f=%.1f px, σ/f=%.4f, halves differ by %.4f, fov %.1f°",
            focal,
            sigma / focal,
            disagreement,
            fov,
        )
        return unobservable()
    return FocalEstimate(
        Camera("SIMPLE_PINHOLE", width, height, (focal, width / 2.0, height / 2.0)), None, stats
    )
