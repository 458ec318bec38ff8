"""Tracks through query keypoints: a query keypoint matched in several references links those
references' keypoints, which can then be triangulated from the (posed) references alone.

Query keypoints are identified by their pixel coordinates: the pipeline takes every match's
query position from the one keypoint array, so equal coordinates mean the same keypoint. With
``merge_px > 0`` (dense matchers) coordinates are snapped to a ``merge_px`` grid first, an
approximation of merging keypoints within ``merge_px`` (neighbours across a cell border stay
apart).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.estimators.correspondences import StackedMatches, unique_points
from services.estimators.options import EstimatorOptions
from services.estimators.poselib_bridge import (
    estimate_absolute_pose,
    ransac_options,
    refine_absolute_pose,
)
from services.estimators.ransac import Deadline
from services.estimators.robust_scale import adaptive_threshold_px
from services.geometry.camera import Camera
from services.geometry.joint_refinement import PointObservations, refine_pose_and_points
from services.geometry.projection import pixels_from_camera_points
from services.geometry.rigid import Rigid3d
from services.geometry.triangulation import TriangulatedTracks, ransac_triangulate
from services.types import BoolArray, FloatArray, IntArray

# the fewest points the joint refinement of pose and points runs on
JOINT_MIN_POINTS = 6


@dataclass(frozen=True)
class Tracks:
    """T tracks over V references.

    Attributes:
        match_index: (T, V) index into the stacked matches of the track's match in each
            reference, −1 where the reference does not observe it.
        query_match: (T,) one stacked match of each track (for the query pixel / ray).
    """

    match_index: IntArray
    query_match: IntArray

    @property
    def observed(self) -> BoolArray:
        return self.match_index >= 0

    @property
    def size(self) -> int:
        return int(self.match_index.shape[0])

    def subset(self, rows: BoolArray | IntArray) -> Tracks:
        """The tracks selected by a (T,) mask or an index array."""
        return Tracks(self.match_index[rows], self.query_match[rows])

    def multi_view(self) -> Tracks:
        """The tracks observed by at least two references (the triangulable ones)."""
        return self.subset(self.observed.sum(axis=1) >= 2)


def build_tracks(stacked: StackedMatches, merge_px: float = 0.0) -> Tracks:
    """Group the stacked matches by query keypoint.

    Args:
        merge_px: grid size for merging nearby query keypoints; 0 = exact equality.
    """
    n = stacked.size
    num_refs = stacked.offsets.shape[0] - 1
    if n == 0:
        return Tracks(np.zeros((0, num_refs), np.int64), np.zeros(0, np.int64))
    keys = np.floor(stacked.query_xy / merge_px) if merge_px > 0 else stacked.query_xy
    _, first, track_of = unique_points(keys)
    match_index = np.full((first.shape[0], num_refs), -1, dtype=np.int64)
    # later matches of the same keypoint in the same reference overwrite earlier ones
    match_index[track_of, stacked.ref_index] = np.arange(n)
    return Tracks(match_index, first.astype(np.int64))


def triangulate_tracks(
    stacked: StackedMatches,
    tracks: Tracks,
    threshold_px: float,
    views: IntArray | None = None,
    min_angle_deg: float = 1.0,
    deadline: Deadline | None = None,
) -> TriangulatedTracks:
    """RANSAC-triangulate the tracks from the references (all, or the given ``views``).

    Returns ``TriangulatedTracks`` over the T tracks and the chosen views' columns; none of
    them valid once ``deadline`` has passed (it is checked between view pairs: with 100
    references there are 4950).
    """
    cols = np.arange(tracks.match_index.shape[1]) if views is None else views
    mi = tracks.match_index[:, cols]
    observed = mi >= 0
    normalized = stacked.ref_norm[np.where(observed, mi, 0)]
    R = stacked.R_ref[cols]
    C = stacked.C_ref[cols]
    projections = np.concatenate([R, -(R @ C[:, :, None])], axis=2)
    starts, ends = stacked.offsets[cols], stacked.offsets[cols + 1]
    focals = np.where(ends > starts, stacked.ref_focal[np.minimum(starts, stacked.size - 1)], 1.0)
    return ransac_triangulate(
        normalized,
        observed,
        projections,
        focals,
        C,
        threshold_px,
        min_angle_deg,
        stop=deadline.expired if deadline is not None else None,
    )


@dataclass(frozen=True)
class TrackPose:
    """Query pose from triangulated tracks: pose, (T,) 2D–3D inlier mask, iterations."""

    pose: Rigid3d
    inliers: BoolArray
    iterations: int


def pose_from_tracks(
    stacked: StackedMatches,
    tracks: Tracks,
    triangulated: TriangulatedTracks,
    query_camera: Camera,
    options: EstimatorOptions,
    deadline: Deadline,
    calls_left: int = 1,
) -> TrackPose | None:
    """P3P LO-RANSAC (PoseLib, reprojection threshold ``max_error_px``) with non-linear
    refinement on the query keypoints of the valid tracks and their triangulated points."""
    valid = np.flatnonzero(triangulated.valid)
    if valid.size < 4:
        return None
    ransac = ransac_options(
        options.ransac,
        deadline,
        calls_left,
        reprojection_px=options.ransac.max_error_px,
        num_matches=int(valid.size),
    )
    out = estimate_absolute_pose(
        stacked.query_xy[tracks.query_match[valid]],
        triangulated.points[valid],
        query_camera,
        ransac,
        options.ransac.max_error_px / 4.0,
    )
    if out is None:
        return None
    inliers = np.zeros(tracks.size, dtype=bool)
    inliers[valid[out[1]]] = True
    return TrackPose(out[0], inliers, out[2])


def refine_on_points(
    pose: Rigid3d,
    points3d: FloatArray,
    query_xy: FloatArray,
    query_camera: Camera,
    options: EstimatorOptions,
    deadline: Deadline,
    rounds: int = 3,
    min_points: int = 6,
    initial_px: float | None = None,
) -> tuple[Rigid3d, int]:
    """Refine the query pose on 2D–3D matches (PoseLib absolute-pose refinement, Cauchy loss)
    ``rounds`` times; each round keeps the points that reproject within an adaptive threshold
    (3σ of the errors below ``max_error_px``, at least 1 px; below ``initial_px`` instead in
    the first round, which lets a coarse initial pose converge). Returns the pose and the
    number of points used in the last round (0 if it never refined)."""
    used = 0
    for round_index in range(rounds):
        if deadline.expired():
            break
        err = reprojection_errors(pose, points3d, query_xy, query_camera)
        cap = (
            initial_px
            if round_index == 0 and initial_px is not None
            else options.ransac.max_error_px
        )
        thr = adaptive_threshold_px(err, cap)
        inl = err < thr
        if inl.sum() < min_points:
            break
        pose = refine_absolute_pose(query_xy[inl], points3d[inl], query_camera, pose, thr / 4.0)
        used = int(inl.sum())
    return pose, used


def refine_keeping_support(
    pose: Rigid3d,
    points3d: FloatArray,
    query_xy: FloatArray,
    query_camera: Camera,
    options: EstimatorOptions,
    deadline: Deadline,
) -> tuple[Rigid3d, int]:
    """``refine_on_points``, whose adaptive threshold and tight loss sharpen a RANSAC pose on
    its best-fitting points, kept only when at least as many of the points reproject within
    ``max_error_px`` of the refined pose as of ``pose`` (with a few dozen points the adaptive
    threshold can fit a pose that fewer of them support). Returns the pose and the points the
    refinement used (0 when ``pose`` is kept)."""
    refined, used = refine_on_points(pose, points3d, query_xy, query_camera, options, deadline)
    limit = options.ransac.max_error_px
    if used == 0 or support(refined, points3d, query_xy, query_camera, limit) < support(
        pose, points3d, query_xy, query_camera, limit
    ):
        return pose, 0
    return refined, used


def reprojection_errors(
    pose: Rigid3d, points3d: FloatArray, query_xy: FloatArray, query_camera: Camera
) -> FloatArray:
    """Pixel distance of each point's projection by ``pose`` from its query keypoint (inf for
    a point on or behind the camera's plane)."""
    projected = pixels_from_camera_points(query_camera, pose.apply(points3d))
    err = np.linalg.norm(projected - query_xy, axis=1)
    return np.where(np.isfinite(err), err, np.inf)


@dataclass(frozen=True)
class JointPoints:
    """A query's triangulated points that fit its pose, ready for a joint refinement.

    Attributes:
        points: (U, 3) the points that reproject within ``threshold``.
        query_normalized: (U, 2) their query keypoints, normalised coordinates.
        references: the reference observations that triangulated them.
        threshold: the adaptive threshold (pixels) they reproject within.
        all_points: (P, 3) every triangulated point, and ``all_query_xy`` (P, 2) its query
            pixel: what a refined pose's support is counted on.
    """

    points: FloatArray
    query_normalized: FloatArray
    references: PointObservations
    threshold: float
    all_points: FloatArray
    all_query_xy: FloatArray


def joint_points(
    stacked: StackedMatches,
    tracks: Tracks,
    triangulated: TriangulatedTracks,
    pose: Rigid3d,
    query_camera: Camera,
    options: EstimatorOptions,
    min_points: int = JOINT_MIN_POINTS,
) -> JointPoints | None:
    """The triangulated points of ``tracks`` that reproject within the adaptive threshold of
    ``pose`` (``refine_on_points``' last round), each with the reference observations that
    triangulated it; None with fewer than ``min_points``."""
    valid = np.flatnonzero(triangulated.valid)
    points = triangulated.points[valid]
    tracks = tracks.subset(valid)
    query_xy = stacked.query_xy[tracks.query_match]
    errors = reprojection_errors(pose, points, query_xy, query_camera)
    threshold = adaptive_threshold_px(errors, options.ransac.max_error_px)
    used = errors < threshold
    if used.sum() < max(min_points, 1):
        return None
    point_of, view_of = np.nonzero(triangulated.inliers[valid][used])
    starts = stacked.offsets[:-1]
    rotations = stacked.R_ref
    observations = PointObservations(
        point_of=point_of,
        camera_of=view_of,
        normalized=stacked.ref_norm[tracks.match_index[used][point_of, view_of]],
        rotations=rotations,
        translations=-(rotations @ stacked.C_ref[:, :, None])[:, :, 0],
        focals=stacked.ref_focal[np.minimum(starts, stacked.size - 1)],
    )
    return JointPoints(
        points[used],
        stacked.query_norm[tracks.query_match[used]],
        observations,
        threshold,
        points,
        query_xy,
    )


def refine_with_points(
    stacked: StackedMatches,
    tracks: Tracks,
    triangulated: TriangulatedTracks,
    pose: Rigid3d,
    query_camera: Camera,
    options: EstimatorOptions,
    deadline: Deadline,
) -> tuple[Rigid3d, int]:
    """``pose`` refined jointly with the ``joint_points`` of ``tracks``
    (``services.geometry.joint_refinement``; Cauchy loss at a quarter of the threshold). Kept
    only when at least as many of the points reproject within ``max_error_px`` of it as of
    ``pose``. Returns the pose and the points it rests on (0 when ``pose`` is kept)."""
    found = joint_points(stacked, tracks, triangulated, pose, query_camera, options)
    if found is None or deadline.expired():
        return pose, 0
    refined, _ = refine_pose_and_points(
        pose,
        found.points,
        found.query_normalized,
        float(np.mean(query_camera.focal_lengths)),
        found.references,
        found.threshold / 4.0,
        stop=deadline.expired,
    )
    limit = options.ransac.max_error_px
    points, query_xy = found.all_points, found.all_query_xy
    if support(refined, points, query_xy, query_camera, limit) < support(
        pose, points, query_xy, query_camera, limit
    ):
        return pose, 0
    return refined, len(found.points)


def support(
    pose: Rigid3d, points3d: FloatArray, query_xy: FloatArray, query_camera: Camera, limit: float
) -> int:
    """How many of the points reproject within ``limit`` pixels of their query keypoints."""
    errors = reprojection_errors(pose, points3d, query_xy, query_camera)
    return int(np.count_nonzero(errors < limit))
