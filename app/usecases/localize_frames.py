"""Localize query frames that come with their AR-session poses, and answer
``map_from_session``. One frame goes through the ordinary localization (any estimator); two or
more are localized jointly as a rig (``services.localization.frames``)."""

from __future__ import annotations

from dataclasses import dataclass, replace

from app.usecases.localize import LocalizeContext, LocalizeRequest, localize
from services.errors import InvalidInputError
from services.estimators.rig_pose import RIG_METHOD
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d
from services.localization.frames import (
    QueryFrame,
    SessionLocalizationResult,
    align_single_frame,
    localize_frames,
)
from services.runtime.worker_slots import holding


@dataclass(frozen=True)
class SessionFrame:
    """A frame's intrinsics (None: the request's camera) and its ``cam_from_session``
    (COLMAP camera axes, metres)."""

    camera: Camera | None
    cam_from_session: Rigid3d


def localize_with_session(
    context: LocalizeContext,
    map_id: str,
    request: LocalizeRequest,
    frames: list[SessionFrame],
    images: list[bytes],
    depth_bytes: bytes | None = None,
    *,
    max_frames: int,
) -> SessionLocalizationResult:
    """Localize ``images`` (frame ``i`` described by ``frames[i]``) against the map.

    Args:
        max_frames: the most frames a request may send.

    Raises:
        NotFoundError: unknown map.
        InvalidInputError: frame and image counts differ, too many frames, depth or an
            estimator other than the joint one with several frames, or an unusable image,
            camera or parameter.
    """
    if len(frames) != len(images):
        raise InvalidInputError(
            f"params.frames describes {len(frames)} frames but {len(images)} images were "
            "uploaded: one frame per image part, in order"
        )
    if not 1 <= len(frames) <= max_frames:
        raise InvalidInputError(f"a request carries 1 to {max_frames} frames, got {len(frames)}")
    if len(frames) == 1:
        frame = frames[0]
        single = replace(request, camera=frame.camera or request.camera)
        result = localize(context, map_id, single, images[0], depth_bytes)
        return align_single_frame(result, frame.cam_from_session)
    if depth_bytes is not None:
        raise InvalidInputError("depth: a query of several frames takes no depth upload")
    if request.estimator not in (None, RIG_METHOD):
        raise InvalidInputError(
            f"estimator: several frames are localized jointly by {RIG_METHOD} (local "
            f"triangulation, generalized absolute pose); {request.estimator} takes one frame"
        )
    # the joint method is the only one: the estimator the parameters resolve is not used
    localizer, params, store = context.map_engine(map_id, replace(request, estimator=None))
    query_frames = [
        QueryFrame(image, frame.camera, frame.cam_from_session)
        for image, frame in zip(images, frames, strict=True)
    ]
    # each frame counted as a query of its own: decoded, described and matched
    memory = sum(localizer.upload_memory_mib(image, False, params.top_k) for image in images)
    with holding(context.slots, memory):
        return localize_frames(localizer, query_frames, params, store, context.spare)
