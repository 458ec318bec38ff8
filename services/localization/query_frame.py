"""How a query frame from a phone relates to the map's references: its intrinsics adapted to
the upload, the quarter turns that may bring it upright, and the gravity check of its pose.

Learned features (ALIKED, DISK) are not rotation invariant and references are captured
upright, so a sideways query is extracted and matched turned upright; its keypoints are mapped
back to the upload before estimation, so the pose is always the uploaded image's.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from services.errors import InvalidInputError
from services.estimators.base import EstimateResult, FailureReason, ReferenceObservation
from services.features.base import LocalFeatures
from services.geometry.camera import Camera
from services.geometry.gravity import gravity_error_deg, references_down, unit, upright_turn
from services.geometry.intrinsics_adaptation import (
    CameraAdaptation,
    adapt_camera,
    rotate_points,
    rotated_from_camera,
    rotated_size,
)
from services.localization.exif_orientation import exif_orientation, orientation_rotation_deg
from services.types import FloatArray, UInt8Array

# the turns tried, in order, when nothing tells which way is up: as uploaded, then the two
# portrait/landscape mix-ups, then upside down
SEARCH_TURNS = (0, 90, 270, 180)
DEFAULT_GRAVITY_MAX_ANGLE_DEG = 5.0


@dataclass(frozen=True)
class GravityHint:
    """A measured gravity direction (ARKit, ARCore and every phone have it).

    Attributes:
        down: (3,) direction of gravity in the frame of the request's camera (of the upload
            when the request has none), COLMAP axes (x right, y down, z forward); any length.
        max_angle_deg: poses whose predicted gravity is further off are rejected.
        map_down: (3,) the map's down in world coordinates; None takes the retrieved
            references' mean image down (``references_down``).
    """

    down: FloatArray
    max_angle_deg: float = DEFAULT_GRAVITY_MAX_ANGLE_DEG
    map_down: FloatArray | None = None


@dataclass(frozen=True)
class QueryFrameHints:
    """What an AR client says about its frame.

    Attributes:
        camera_rotation_deg: clockwise turn from the camera's image to the upload as decoded
            (None: decided by the sizes and the EXIF orientation, see ``adapt_camera``).
        gravity: measured gravity, used to turn the query upright and to check the pose.
        rotation_search: without a usable gravity, try the other quarter turns (in
            ``SEARCH_TURNS`` order, within the time budget) when the upload as it is fails.
    """

    camera_rotation_deg: int | None = None
    gravity: GravityHint | None = None
    rotation_search: bool = True


@dataclass(frozen=True)
class QueryFrame:
    """The query as the engine uses it.

    Attributes:
        camera: intrinsics of the decoded upload; None when the request gave none.
        adaptation: how the request's camera was adapted (None without a camera).
        gravity: (3,) unit gravity in the decoded upload's camera frame, or None.
        turns: clockwise quarter turns to extract the query at, tried in order.
    """

    camera: Camera | None
    adaptation: CameraAdaptation | None
    gravity: FloatArray | None
    turns: tuple[int, ...]


def resolve_query_frame(
    image_bytes: bytes, image: UInt8Array, camera: Camera | None, hints: QueryFrameHints
) -> QueryFrame:
    """The query frame of an upload (``image``: decoded from ``image_bytes``, EXIF applied).

    Raises:
        InvalidInputError: the camera does not fit the upload (see ``adapt_camera``), or a
            mirroring EXIF orientation with a camera.
    """
    adaptation = None
    if camera is not None:
        orientation = exif_orientation(image_bytes)
        adaptation = adapt_camera(
            camera,
            (image.shape[1], image.shape[0]),
            exif_rotation_deg=orientation_rotation_deg(orientation),
            exif_orientation=orientation,
            rotation_deg=hints.camera_rotation_deg,
        )
    gravity = None
    if hints.gravity is not None:
        try:
            gravity = unit(hints.gravity.down)
            if hints.gravity.map_down is not None:
                unit(hints.gravity.map_down)
        except ValueError as exc:
            raise InvalidInputError(f"gravity: {exc}") from None
        if adaptation is not None:
            gravity = rotated_from_camera(adaptation.rotation_deg) @ gravity
    turn = upright_turn(gravity) if gravity is not None else None
    if turn is not None:
        turns: tuple[int, ...] = (turn,)
    elif hints.rotation_search:
        turns = SEARCH_TURNS
    else:
        turns = (0,)
    return QueryFrame(adaptation.camera if adaptation else None, adaptation, gravity, turns)


def turn_image(image: UInt8Array, turn: int) -> UInt8Array:
    """(H, W, 3) image turned clockwise by ``turn`` degrees (a quarter-turn multiple)."""
    turned: UInt8Array = np.ascontiguousarray(np.rot90(image, k=-(turn // 90)))
    return turned


def features_in_upload(features: LocalFeatures, turn: int) -> LocalFeatures:
    """Features extracted on the upload turned by ``turn``, with keypoints mapped back to the
    upload (COLMAP pixel convention) and ``image_size`` the upload's."""
    if turn == 0:
        return features
    width, height = features.image_size
    back = (360 - turn) % 360
    keypoints = rotate_points(features.keypoints.astype(np.float64), back, width, height).astype(
        np.float32
    )
    upload_width, upload_height = rotated_size(width, height, back)
    return replace(features, keypoints=keypoints, image_size=(upload_width, upload_height))


def check_gravity(
    outcome: EstimateResult,
    gravity: FloatArray | None,
    hint: GravityHint | None,
    references: list[ReferenceObservation],
) -> EstimateResult:
    """``outcome`` with ``gravity_error_deg`` in its stats, or a ``gravity_mismatch`` failure
    when its pose disagrees with the measured gravity by more than the hint's maximum."""
    if outcome.cam_from_world is None or gravity is None or hint is None:
        return outcome
    world_down = (
        hint.map_down
        if hint.map_down is not None
        else references_down([ref.cam_from_world for ref in references])
    )
    error = gravity_error_deg(outcome.cam_from_world, gravity, world_down)
    stats = {**outcome.stats, "gravity_error_deg": error}
    if error > hint.max_angle_deg:
        return EstimateResult.failure(FailureReason.GRAVITY_MISMATCH, references, stats)
    return replace(outcome, stats=stats)
