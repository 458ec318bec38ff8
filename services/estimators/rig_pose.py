"""Joint pose of several query frames whose relative poses are known (an AR session's device
poses): the frames form a generalized camera (rig) whose frame is the session, and one rigid
transform ``session_from_map`` places the whole rig in the map.

Method (local triangulation, the most accurate family of Panek et al. 2025, "A Guide to
Structureless Visual Localization", generalised to a rig):

1. per frame, tracks through each query keypoint over that frame's retrieved references are
   RANSAC-triangulated from the references alone (``tracks.triangulate_tracks``, threshold
   ``TriangulationOptions.max_error_px``);
2. all frames' query keypoints ↔ triangulated points go into one generalized absolute pose
   problem: GP3P in LO-RANSAC with refinement (PoseLib ``estimate_generalized_absolute_pose``,
   reprojection threshold ``RansacOptions.max_error_px``), camera ``i`` at ``cam_i_from_session``;
   the pose is then refined jointly with the frames' points that fit it, each with the
   reference observations that triangulated it (one bundle adjustment whose only free cameras
   are the rig's), as a single frame's ``local_tri_all`` answer is, and kept when as many of
   the points support it;
3. each frame's pose ``cam_i_from_map = cam_i_from_session ∘ session_from_map``; its inliers are
   its matches within ``max_error_px`` Sampson error, as for every single-frame estimator;
4. acceptance pools the frames: inliers, references with inliers and verified 3D points
   (``services.estimators.verification``) are summed over frames and checked against
   ``VerificationOptions``.

A frame with too few points to be localized alone (P3P needs four, the verification ten) still
adds its points to the joint problem: the rig needs them only in total.

Consistency (the session poses are checked against the images, not trusted): every frame with
at least ``OWN_POSE_MIN_INLIERS`` triangulated points is also localized alone (P3P LO-RANSAC on
its own 2D–3D matches; a *witness* when its own pose has that many point inliers). A witness
whose own pose lies farther than ``consistency_bound_m`` (max(0.25 m, 5 % of the session extent,
5 % of its median scene depth)) or 5° from its pose under the joint estimate is *inconsistent*:
its session pose and its image disagree. When the witnesses that agree outnumber the
inconsistent ones, the inconsistent frames are dropped (no pose, no inliers) and the joint
estimate is redone without them; otherwise, or when the redone estimate still has an
inconsistent frame, the answer is ``inconsistent_frames``. A joint pose that fits fewer than
``MIN_POINT_INLIER_SHARE`` of the frames' triangulated points is ``no_consensus``: the points
agree by chance, or were triangulated wrong. The confidence reads the agreement:
the pooled ``confidence_from_inliers`` times the fraction of frames *supported* by the joint
estimate (at least ``MIN_FRAME_SUPPORT`` of a frame's 2D–3D points are inliers of the joint
pose), so a dropped frame or one without support lowers it; and, as a single frame's, it is
capped by the pose's uncertainty (``services.estimators.uncertainty.rig_pose_uncertainty``:
every frame's verified points and the references they rest on, carried onto the first frame).

Scale: the session is metric (ARKit, ARCore, WebXR) and the map is taken to be metric; a map in
other units gives a wrong ``session_from_map`` (no scale is estimated).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np

from services.estimators.base import FailureReason, ReferenceObservation, confidence_from_inliers
from services.estimators.correspondences import (
    StackedMatches,
    pose_sampson_errors_px,
    stack_matches,
)
from services.estimators.options import EstimatorOptions
from services.estimators.poselib_bridge import (
    estimate_absolute_pose,
    estimate_generalized_absolute_pose,
    ransac_options,
)
from services.estimators.ransac import Deadline
from services.estimators.tracks import (
    JOINT_MIN_POINTS,
    JointPoints,
    Tracks,
    build_tracks,
    joint_points,
    support,
    triangulate_tracks,
)
from services.estimators.uncertainty import (
    PoseUncertainty,
    capped_confidence,
    rig_pose_uncertainty,
    uncertainty_stats,
)
from services.estimators.verification import CheckedTracks, check_structure
from services.geometry.camera import Camera
from services.geometry.joint_refinement import PointObservations, RigViews, refine_pose_and_points
from services.geometry.rigid import Rigid3d, rotation_error_deg
from services.geometry.triangulation import TriangulatedTracks
from services.types import BoolArray, FloatArray

logger = logging.getLogger(__name__)

# the method's name in results (the family of ``local_tri_all``)
RIG_METHOD = "local_tri_all"

# the least share of the frames' triangulated points that the joint pose must fit: on pairs
# of dev-set queries every answer more than 1 m off fitted 23-36 % of them, and 6 of 574 right
# answers fitted less than 40 % (docs/benchmarks/2026-12-02-session-frames.md)
MIN_POINT_INLIER_SHARE = 0.4
# a frame is localized alone (a witness of its session pose) from this many 2D–3D inliers
OWN_POSE_MIN_INLIERS = 15
# a frame's own pose and its joint pose agree within max(these) metres ...
CONSISTENCY_MIN_M = 0.25
CONSISTENCY_EXTENT_FRACTION = 0.05  # of the session extent (largest distance between frames)
CONSISTENCY_DEPTH_FRACTION = 0.05  # of the frame's median depth of its own inlier points
# ... and this many degrees
CONSISTENCY_MAX_DEG = 5.0
# a frame supports the joint estimate with this many 2D–3D inliers of the joint pose (Sampson
# inliers are no evidence: an unrelated image has a few by chance)
MIN_FRAME_SUPPORT = 3


@dataclass(frozen=True)
class RigFrame:
    """One query frame of the rig.

    Attributes:
        camera: its intrinsics.
        cam_from_session: its pose in the session (COLMAP camera axes).
        references: its retrieved references and matches (query pixels are this frame's).
    """

    camera: Camera
    cam_from_session: Rigid3d
    references: list[ReferenceObservation]


@dataclass(frozen=True)
class RigEstimate:
    """The joint answer.

    Attributes:
        session_from_map: the rig's pose in the map, None on failure.
        inliers: per frame, one (M,) mask per reference: matches within ``max_error_px``
            Sampson error of the frame's pose (all False on failure).
        point_inliers: per frame, its 2D–3D inliers of the generalized absolute pose.
        confidence: ``confidence_from_inliers`` of the pooled inliers times the fraction of
            supported frames, capped by the uncertainty (``capped_confidence``), 0 on failure.
        stats: numbers describing the run.
        failure_reason: set exactly when ``session_from_map`` is None.
        dropped: indices of the frames left out as inconsistent (no pose, no inliers).
        uncertainty: the first frame's pose uncertainty under the joint estimate
            (``rig_pose_uncertainty``); None on failure or without enough verified points.
    """

    session_from_map: Rigid3d | None
    inliers: list[list[BoolArray]]
    point_inliers: list[int]
    confidence: float = 0.0
    stats: dict[str, float] = field(default_factory=dict)
    failure_reason: FailureReason | None = None
    dropped: frozenset[int] = frozenset()
    uncertainty: PoseUncertainty | None = None

    @property
    def num_inliers(self) -> int:
        return int(sum(int(m.sum()) for masks in self.inliers for m in masks))

    def cam_from_map(self, frame: RigFrame, index: int | None = None) -> Rigid3d | None:
        """``frame``'s pose in the map (None on failure, or when frame ``index`` was dropped)."""
        if self.session_from_map is None or (index is not None and index in self.dropped):
            return None
        return frame.cam_from_session.compose(self.session_from_map)


@dataclass(frozen=True)
class _FramePoints:
    """A frame's query pixels (P, 2) and triangulated map points (P, 3), and the
    triangulation of its tracks they come from (None without tracks)."""

    stacked: StackedMatches
    tracks: Tracks
    pixels: FloatArray
    points: FloatArray
    triangulated: TriangulatedTracks | None = None


def _frame_points(frame: RigFrame, options: EstimatorOptions, deadline: Deadline) -> _FramePoints:
    """The frame's triangulated points; none once ``deadline`` has passed."""
    stacked = stack_matches(frame.camera, frame.references)
    tracks = build_tracks(stacked, options.triangulation.track_merge_px).multi_view()
    if tracks.size == 0 or deadline.expired():
        return _FramePoints(stacked, tracks, np.zeros((0, 2)), np.zeros((0, 3)))
    tri = triangulate_tracks(stacked, tracks, options.triangulation.max_error_px, deadline=deadline)
    valid = np.flatnonzero(tri.valid)
    return _FramePoints(
        stacked, tracks, stacked.query_xy[tracks.query_match[valid]], tri.points[valid], tri
    )


def _no_masks(frames: list[RigFrame]) -> list[list[BoolArray]]:
    return [[np.zeros(ref.num_matches, bool) for ref in frame.references] for frame in frames]


def _failure(reason: FailureReason, frames: list[RigFrame], stats: dict[str, float]) -> RigEstimate:
    return RigEstimate(None, _no_masks(frames), [0] * len(frames), 0.0, stats, reason)


def estimate_rig_pose(frames: list[RigFrame], options: EstimatorOptions) -> RigEstimate:
    """``session_from_map`` of the rig from all frames' matches jointly (see the module).

    Failures: ``no_references`` (no frame retrieved any), ``too_few_matches`` (fewer than four
    triangulated points over all frames), ``degenerate_geometry`` (many tracks, too few
    triangulable, or a singular system), ``no_consensus`` (RANSAC found nothing, or the pooled
    support is below ``options.verification``), ``inconsistent_frames`` (frames localized alone
    disagree with their session poses, see the module), ``time_budget_exceeded``.
    """
    stats: dict[str, float] = {"frames": float(len(frames))}
    if not any(frame.references for frame in frames):
        return _failure(FailureReason.NO_REFERENCES, frames, stats)
    deadline = Deadline(options.time_budget_s)
    try:
        return _estimate(frames, options, deadline, stats)
    except np.linalg.LinAlgError:  # a singular system the checks let through
        logger.warning("rig pose: singular linear system", exc_info=True)
        return _failure(FailureReason.DEGENERATE_GEOMETRY, frames, stats)


def _estimate(
    frames: list[RigFrame], options: EstimatorOptions, deadline: Deadline, stats: dict[str, float]
) -> RigEstimate:
    per_frame = [_frame_points(frame, options, deadline) for frame in frames]
    counts = [int(p.pixels.shape[0]) for p in per_frame]
    stats["tracks_multi_view"] = float(sum(p.tracks.size for p in per_frame))
    stats["points_triangulated"] = float(sum(counts))
    if deadline.expired():
        return _failure(FailureReason.TIME_BUDGET_EXCEEDED, frames, stats)
    if sum(counts) < 4:
        reason = (
            FailureReason.DEGENERATE_GEOMETRY
            if stats["tracks_multi_view"] >= 20
            else FailureReason.TOO_FEW_MATCHES
        )
        return _failure(reason, frames, stats)
    threshold = options.ransac.max_error_px
    own = [
        _own_pose(frame, points, options, deadline)
        for frame, points in zip(frames, per_frame, strict=True)
    ]
    witnesses = [i for i, pose in enumerate(own) if pose is not None]
    extent = _session_extent(frames)
    stats["frames_localized_alone"] = float(len(witnesses))
    stats["frames_inconsistent"] = 0.0
    dropped: set[int] = set()
    for attempt in range(2):
        used = [i for i, c in enumerate(counts) if c > 0 and i not in dropped]
        if sum(counts[i] for i in used) < 4:
            return _failure(FailureReason.INCONSISTENT_FRAMES, frames, stats)
        found = estimate_generalized_absolute_pose(
            [per_frame[i].pixels for i in used],
            [per_frame[i].points for i in used],
            [frames[i].cam_from_session for i in used],
            [frames[i].camera for i in used],
            ransac_options(
                options.ransac,
                deadline,
                reprojection_px=threshold,
                num_matches=sum(counts[i] for i in used),
            ),
            threshold / 4.0,
        )
        if found is None:
            return _failure(FailureReason.NO_CONSENSUS, frames, stats)
        session_from_map, point_masks, iterations = found
        inconsistent = [
            i
            for i in witnesses
            if i not in dropped
            and not _agrees(own[i], frames[i].cam_from_session.compose(session_from_map), extent)
        ]
        if not inconsistent:
            break
        stats["frames_inconsistent"] = float(len(inconsistent) + len(dropped))
        agreeing = len(witnesses) - len(dropped) - len(inconsistent)
        if attempt > 0 or agreeing <= len(inconsistent):
            return _failure(FailureReason.INCONSISTENT_FRAMES, frames, stats)
        dropped.update(inconsistent)
    stats["frames_dropped"] = float(len(dropped))
    point_inliers = [0] * len(frames)
    for i, mask in zip(used, point_masks, strict=True):
        point_inliers[i] = int(mask.sum())
    stats["iterations"] = float(iterations)
    stats["points_inliers"] = float(sum(point_inliers))
    stats["frames_with_points"] = float(sum(c > 0 for c in point_inliers))
    share = sum(point_inliers) / max(sum(counts[i] for i in used), 1)
    stats["points_inlier_share"] = share
    if share < MIN_POINT_INLIER_SHARE:
        return _failure(FailureReason.NO_CONSENSUS, frames, stats)
    session_from_map = _refined_with_points(
        frames, per_frame, used, session_from_map, options, deadline, stats
    )

    poses = [frame.cam_from_session.compose(session_from_map) for frame in frames]
    inliers: list[list[BoolArray]] = []
    checks: list[CheckedTracks | None] = []
    for i, (frame, points, pose) in enumerate(zip(frames, per_frame, poses, strict=True)):
        if deadline.expired():  # a pose not verified in time is no answer
            return _failure(FailureReason.TIME_BUDGET_EXCEEDED, frames, stats)
        if not frame.references or i in dropped:
            inliers.append([np.zeros(ref.num_matches, bool) for ref in frame.references])
            checks.append(None)
            continue
        errors = pose_sampson_errors_px(points.stacked, pose.rotation[None], pose.center[None])[0]
        masks = points.stacked.split(errors < threshold)
        inliers.append(masks)
        checks.append(check_structure(frame.camera, pose, frame.references, masks, threshold))
    verified = sum(checked.check.num_verified_points for checked in checks if checked)
    estimate = _accept(
        session_from_map, frames, inliers, point_inliers, verified, options, stats, dropped
    )
    if estimate.session_from_map is None:
        return estimate
    uncertainty = rig_pose_uncertainty(
        poses, [frame.camera for frame in frames], checks, options.uncertainty
    )
    stats.update(uncertainty_stats(uncertainty))
    confidence = capped_confidence(estimate.confidence, uncertainty, options.uncertainty, False)
    return replace(estimate, confidence=confidence, uncertainty=uncertainty)


def _refined_with_points(
    frames: list[RigFrame],
    per_frame: list[_FramePoints],
    used: list[int],
    session_from_map: Rigid3d,
    options: EstimatorOptions,
    deadline: Deadline,
    stats: dict[str, float],
) -> Rigid3d:
    """The rig's pose refined jointly with its frames' points, as a single frame's is
    (``tracks.refine_with_points``): each used frame's triangulated points that fit its pose
    (``tracks.joint_points``; ``JOINT_MIN_POINTS`` over all frames, as a frame too weak alone
    still places the rig), with the reference observations that triangulated them, in one
    bundle adjustment whose only free cameras are the rig's (``refine_pose_and_points`` with
    ``RigViews``). Kept only when at least as many of the frames' points reproject within
    ``max_error_px`` as of ``session_from_map`` (``points_refined_jointly`` in ``stats``)."""
    found: dict[int, JointPoints] = {}
    poses = {i: frames[i].cam_from_session.compose(session_from_map) for i in used}
    for i in used:
        points = per_frame[i].triangulated
        if points is not None:
            joint = joint_points(
                per_frame[i].stacked,
                per_frame[i].tracks,
                points,
                poses[i],
                frames[i].camera,
                options,
                min_points=1,
            )
            if joint is not None:
                found[i] = joint
    total = sum(len(joint.points) for joint in found.values())
    if total < JOINT_MIN_POINTS or deadline.expired():
        return session_from_map
    order = list(found)
    first = poses[order[0]]
    counts = np.cumsum([0] + [len(found[i].points) for i in order])
    cameras = np.cumsum([0] + [len(found[i].references.rotations) for i in order])
    refs = [found[i].references for i in order]
    references = PointObservations(
        point_of=np.concatenate([r.point_of + counts[v] for v, r in enumerate(refs)]),
        camera_of=np.concatenate([r.camera_of + cameras[v] for v, r in enumerate(refs)]),
        normalized=np.concatenate([r.normalized for r in refs]),
        rotations=np.concatenate([r.rotations for r in refs]),
        translations=np.concatenate([r.translations for r in refs]),
        focals=np.concatenate([r.focals for r in refs]),
    )
    rig = RigViews(
        [poses[i].compose(first.inverse()) for i in order],
        np.array([float(np.mean(frames[i].camera.focal_lengths)) for i in order]),
        np.repeat(np.arange(len(order)), np.diff(counts)),
    )
    refined, _ = refine_pose_and_points(
        first,
        np.concatenate([found[i].points for i in order]),
        np.concatenate([found[i].query_normalized for i in order]),
        0.0,
        references,
        float(np.mean([found[i].threshold for i in order])) / 4.0,
        stop=deadline.expired,
        rig=rig,
    )
    moved = frames[order[0]].cam_from_session.inverse().compose(refined)
    limit = options.ransac.max_error_px

    def rig_support(candidate: Rigid3d) -> int:
        return sum(
            support(
                frames[i].cam_from_session.compose(candidate),
                found[i].all_points,
                found[i].all_query_xy,
                frames[i].camera,
                limit,
            )
            for i in order
        )

    if rig_support(moved) < rig_support(session_from_map):
        return session_from_map
    stats["points_refined_jointly"] = float(counts[-1])
    return moved


def _own_pose(
    frame: RigFrame, points: _FramePoints, options: EstimatorOptions, deadline: Deadline
) -> tuple[Rigid3d, float] | None:
    """The frame localized alone from its own 2D–3D matches and the median depth of its inlier
    points, or None when it has fewer than ``OWN_POSE_MIN_INLIERS`` (points or inliers)."""
    count = int(points.pixels.shape[0])
    if count < OWN_POSE_MIN_INLIERS or deadline.expired():
        return None
    threshold = options.ransac.max_error_px
    found = estimate_absolute_pose(
        points.pixels,
        points.points,
        frame.camera,
        ransac_options(options.ransac, deadline, reprojection_px=threshold, num_matches=count),
        threshold / 4.0,
    )
    if found is None or int(found[1].sum()) < OWN_POSE_MIN_INLIERS:
        return None
    pose, mask, _ = found
    depth = pose.apply(points.points[mask])[:, 2]
    return pose, float(np.median(depth))


def _session_extent(frames: list[RigFrame]) -> float:
    """The largest distance between two frames' centres in the session (metres)."""
    centres = np.array([frame.cam_from_session.center for frame in frames])
    return float(np.max(np.linalg.norm(centres[:, None] - centres[None], axis=-1)))


def consistency_bound_m(extent_m: float, depth_m: float) -> float:
    """How far (metres) a frame's own pose may lie from its joint pose."""
    return max(
        CONSISTENCY_MIN_M,
        CONSISTENCY_EXTENT_FRACTION * extent_m,
        CONSISTENCY_DEPTH_FRACTION * max(depth_m, 0.0),
    )


def _agrees(own: tuple[Rigid3d, float] | None, joint: Rigid3d, extent_m: float) -> bool:
    if own is None:
        return True
    pose, depth = own
    moved = float(np.linalg.norm(pose.center - joint.center))
    turned = rotation_error_deg(pose.rotation, joint.rotation)
    return moved <= consistency_bound_m(extent_m, depth) and turned <= CONSISTENCY_MAX_DEG


def _accept(
    session_from_map: Rigid3d,
    frames: list[RigFrame],
    inliers: list[list[BoolArray]],
    point_inliers: list[int],
    verified: int,
    options: EstimatorOptions,
    stats: dict[str, float],
    dropped: set[int],
) -> RigEstimate:
    """The pooled acceptance of ``VerificationOptions`` over all frames, and the confidence
    scaled by the fraction of frames the estimate supports."""
    num_inliers = int(sum(int(m.sum()) for masks in inliers for m in masks))
    references_with_inliers = len(
        {
            ref.image_id
            for frame, masks in zip(frames, inliers, strict=True)
            for ref, m in zip(frame.references, masks, strict=True)
            if int(m.sum()) >= 3
        }
    )
    total = sum(ref.num_matches for frame in frames for ref in frame.references)
    stats.update(
        num_matches=float(total),
        num_inliers=float(num_inliers),
        inlier_ratio=num_inliers / max(total, 1),
        references_with_inliers=float(references_with_inliers),
        verified_points=float(verified),
    )
    acceptance = options.verification
    if (
        num_inliers < acceptance.min_inliers
        or references_with_inliers < acceptance.min_references
        or verified < acceptance.min_verified_points
        or sum(point_inliers) < 4
    ):
        return RigEstimate(None, inliers, point_inliers, 0.0, stats, FailureReason.NO_CONSENSUS)
    supported = sum(1 for n in point_inliers if n >= MIN_FRAME_SUPPORT)
    agreement = supported / len(frames)
    stats["frames_supported"] = float(supported)
    confidence = confidence_from_inliers(num_inliers, references_with_inliers) * agreement
    return RigEstimate(
        session_from_map, inliers, point_inliers, confidence, stats, None, frozenset(dropped)
    )
