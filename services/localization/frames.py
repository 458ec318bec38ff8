"""Localize several query frames with their AR-session poses jointly, and answer
``map_from_session``: the transform that places map content in the client's AR session.

Every frame goes through the single-image stages (decode, extract, retrieve its own top-k,
match); the estimate is joint (``services.estimators.rig_pose``). Limits apply to all frames
together: one time budget, and the pixel limit on the sum of the frames' pixels.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

from services.estimators.rig_pose import RIG_METHOD, RigEstimate, RigFrame, estimate_rig_pose
from services.features.base import LocalFeatures
from services.geometry.camera import Camera, default_camera
from services.geometry.rigid import Rigid3d
from services.imaging.decode import DecodedImage
from services.localization.answer import (
    LocalizationResult,
    RetrievedReference,
    out_of_time,
    retrieved_references,
)
from services.localization.clock import OutOfTimeError, StageClock
from services.localization.localizer import LocalizeParams, Localizer
from services.localization.stages import (
    check_camera_matches,
    decode_frames,
    match,
    retrieve,
)
from services.references.store import ReferenceStore
from services.runtime.spare_workers import SpareWorkers


@dataclass(frozen=True)
class QueryFrame:
    """One uploaded frame.

    Attributes:
        image_bytes: JPEG or PNG.
        camera: its intrinsics (None: ``LocalizeParams.camera``, else the default camera).
        cam_from_session: its pose in the AR session, COLMAP camera axes
            (``services.geometry.session_pose.cam_from_session`` converts ARKit's).
    """

    image_bytes: bytes
    camera: Camera | None
    cam_from_session: Rigid3d


@dataclass(frozen=True)
class FrameResult:
    """One frame of the answer: its pose in the map (None when not localized), its inliers
    (Sampson, over its references), its 2D–3D inliers in the joint estimate (0 for a single
    frame), and its retrieved references."""

    cam_from_world: Rigid3d | None
    num_inliers: int
    num_point_inliers: int
    retrieved: list[RetrievedReference]


@dataclass(frozen=True)
class SessionLocalizationResult:
    """A localization with session poses.

    Attributes:
        result: the summary: ``localized``, ``reason``, ``num_inliers`` and ``confidence`` of
            the joint estimate; ``cam_from_world`` and ``retrieved`` of the first frame.
        map_from_session: maps session coordinates to map coordinates (None when not
            localized).
        frames: one per uploaded frame, in upload order.
    """

    result: LocalizationResult
    map_from_session: Rigid3d | None
    frames: list[FrameResult]

    def below(self, min_confidence: float) -> SessionLocalizationResult:
        """This answer, or, when its joint estimate is less confident than ``min_confidence``,
        the ``low_confidence`` answer: no map_from_session, no frame poses, the first frame's
        pose as the summary's ``candidate``."""
        result = self.result.below(min_confidence)
        if result is self.result:
            return self
        frames = [replace(frame, cam_from_world=None) for frame in self.frames]
        return SessionLocalizationResult(result, None, frames)


def align_single_frame(
    result: LocalizationResult, cam_from_session: Rigid3d
) -> SessionLocalizationResult:
    """``map_from_session`` of one frame localized alone: ``map_from_cam ∘ cam_from_session``."""
    pose = result.cam_from_world
    map_from_session = pose.inverse().compose(cam_from_session) if pose is not None else None
    frame = FrameResult(pose, result.num_inliers, 0, result.retrieved)
    return SessionLocalizationResult(result, map_from_session, [frame])


def localize_frames(
    localizer: Localizer,
    frames: list[QueryFrame],
    params: LocalizeParams,
    store: ReferenceStore,
    spare: SpareWorkers | None = None,
) -> SessionLocalizationResult:
    """Localize ``frames`` (two or more) jointly. ``params.estimator`` is not used: the joint
    method is ``rig_pose`` (reported as ``RIG_METHOD``). A query that cannot be localized is a
    result with ``localized`` False and a reason. ``spare``: the idle workers the frames'
    extraction and matching may borrow (None: all on the calling thread).

    Raises:
        InvalidInputError: an image is unusable or does not fit its camera.
        ImageTooLargeError: the frames together exceed the localizer's pixel limit.
    """
    clock = StageClock(params.time_budget_s)
    try:
        return _localize_frames(localizer, frames, params, store, clock, spare)
    except OutOfTimeError:
        empty = out_of_time(RIG_METHOD, clock.finish())
        return SessionLocalizationResult(empty, None, [FrameResult(None, 0, 0, []) for _ in frames])


def _localize_frames(
    localizer: Localizer,
    frames: list[QueryFrame],
    params: LocalizeParams,
    store: ReferenceStore,
    clock: StageClock,
    spare: SpareWorkers | None,
) -> SessionLocalizationResult:
    lap = clock.lap
    spread = spare.split if spare is not None else None
    images = decode_frames(
        [frame.image_bytes for frame in frames], localizer.max_pixels, localizer.extractor.max_side
    )
    cameras = []
    for frame, image in zip(frames, images, strict=True):
        camera = frame.camera or params.camera or default_camera(image.width, image.height)
        check_camera_matches(camera, image)
        cameras.append(camera)
    lap("decode")

    def extract(run: Sequence[DecodedImage]) -> list[LocalFeatures]:
        """The run's features; fewer once the budget is spent (checked between frames)."""
        out = []
        for image in run:
            if clock.deadline.expired():
                break
            out.append(localizer.extract_features(image))
        return out

    features = spread(extract, images) if spread is not None else extract(images)
    lap("extract")  # raises when a frame was left unextracted
    index = store.retrieval_index()
    retrieved_rows = [
        retrieve(index, localizer.global_descriptor, image.rgb, query, params.top_k, params.prior)
        for image, query in zip(images, features, strict=True)
    ]
    all_ids = list(dict.fromkeys(image_id for rows in retrieved_rows for image_id, _ in rows))
    loaded = {ref.image_id: ref for ref in store.load_references(all_ids)}
    lap("retrieve")
    rig_frames = []
    for query, image, camera, frame, rows in zip(
        features, images, cameras, frames, retrieved_rows, strict=True
    ):
        kept = [(loaded[image_id], score) for image_id, score in rows if image_id in loaded]
        observations = match(localizer.matcher, query, kept, clock.deadline.expired, spread)
        observations = localizer.refine(
            image.rgb,
            (image.width, image.height),
            observations,
            [reference for reference, _ in kept],
            store,
            clock,
            spread=spread,
        )
        rig_frames.append(RigFrame(camera, frame.cam_from_session, observations))
    lap("match")
    estimate = estimate_rig_pose(rig_frames, clock.bound(params.options))
    lap("estimate", check=False)  # the work is done: its answer is kept
    names = {image_id: ref.name for image_id, ref in loaded.items()}
    return _answer(estimate, rig_frames, names, clock.finish()).below(params.min_confidence)


def _answer(
    estimate: RigEstimate,
    frames: list[RigFrame],
    names: dict[str, str],
    timings: dict[str, float],
) -> SessionLocalizationResult:
    frame_results = []
    for i, frame in enumerate(frames):
        masks = estimate.inliers[i]
        frame_results.append(
            FrameResult(
                cam_from_world=estimate.cam_from_map(frame, i),
                num_inliers=int(sum(int(m.sum()) for m in masks)),
                num_point_inliers=estimate.point_inliers[i],
                retrieved=retrieved_references(frame.references, masks, names),
            )
        )
    localized = estimate.session_from_map is not None
    summary = LocalizationResult(
        localized=localized,
        reason=estimate.failure_reason.value if estimate.failure_reason else None,
        estimator=RIG_METHOD,
        cam_from_world=frame_results[0].cam_from_world,
        num_inliers=estimate.num_inliers if localized else 0,
        confidence=estimate.confidence,
        uncertainty=estimate.uncertainty,
        retrieved=frame_results[0].retrieved,
        timings_ms=timings,
        stats=estimate.stats,
    )
    map_from_session = (
        estimate.session_from_map.inverse() if estimate.session_from_map is not None else None
    )
    return SessionLocalizationResult(summary, map_from_session, frame_results)
