"""Capture sessions: a capture's frames with their device poses, aligned to a map and added
to it."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, Field, StrictBool, model_validator

from app.schemas.geo import GpsSchema
from app.schemas.geometry import CameraSchema, PoseSchema
from app.schemas.session import SessionPoseSchema
from app.schemas.text import Name
from app.usecases.captures import NewFrame, similarity_of
from db.models import CaptureFrame, CaptureSession
from db.store import camera_of, gps_of
from services.geometry.rigid import Rigid3d
from services.geometry.session_pose import homogeneous

# a session's and a frame's names together name the reference a frame becomes
# ("<session>/<frame>"), at most 255 characters
MAX_SESSION_NAME = 120
MAX_FRAME_NAME = 120


class CaptureSessionCreate(BaseModel):
    name: Name | None = Field(
        None,
        max_length=MAX_SESSION_NAME,
        description="Unique in the map; the references its frames become are named "
        "<session name>/<frame name>. Default: session-<8 hex digits>",
    )
    metric: StrictBool = Field(
        True,
        description="The frames' poses are in metres (ARKit, ARCore, a metric SLAM): the "
        "session is aligned rigidly. false: its scale is estimated (a similarity; a session "
        "of unknown scale cannot start an empty map)",
    )
    keep_all: StrictBool = Field(
        False,
        description="Add every frame within the anchors' reach. false: a frame is added only "
        "where it adds a view, i.e. no reference or frame kept before it lies within the "
        "map's spacing (the median distance between neighbouring references) looking within "
        "15° of its direction; a session that starts an empty map adds every frame",
    )


class CaptureFrameMetadata(BaseModel):
    """The ``metadata`` form field of a frame upload (a JSON string): its pose in the
    session, as an AR framework reports it (``session_pose``) or as COLMAP writes it
    (``cam_from_session``)."""

    name: Name | None = Field(
        None, max_length=MAX_FRAME_NAME, description="Unique in the session; default: 00000, …"
    )
    camera: CameraSchema | None = Field(
        None, description="Its intrinsics; default: the default camera for the image size"
    )
    session_pose: SessionPoseSchema | None = Field(
        None,
        description="session_from_camera with OpenGL camera axes (ARKit camera.transform, "
        "ARCore Pose, WebXR), as the localize endpoint takes it",
    )
    cam_from_session: PoseSchema | None = Field(
        None, description="x_cam = R · x_session + t, COLMAP camera axes (x right, y down)"
    )
    gps: GpsSchema | None = Field(
        None,
        description="The device's GPS fix when the frame was taken, kept on the reference it "
        "becomes; default: the image's EXIF GPS. A session that starts an empty map "
        "geo-registers it from its frames' fixes (with height)",
    )

    @model_validator(mode="after")
    def _one_pose(self) -> CaptureFrameMetadata:
        if (self.session_pose is None) == (self.cam_from_session is None):
            raise ValueError("give the frame's pose as either session_pose or cam_from_session")
        return self

    def to_new_frame(self) -> NewFrame:
        if self.session_pose is not None:
            pose = self.session_pose.to_cam_from_session()
        else:
            assert self.cam_from_session is not None
            pose = self.cam_from_session.to_rigid()
        return NewFrame(
            self.name,
            self.camera.to_camera() if self.camera else None,
            pose,
            self.gps.to_fix() if self.gps else None,
        )


class CaptureFrameOut(BaseModel):
    id: str = Field(description="The id of the reference it becomes once added")
    name: str
    position: int = Field(description="Its place in the capture order (upload order)")
    camera: CameraSchema
    gps: GpsSchema | None = Field(
        description="Its GPS fix (sent, or read from its EXIF); null when it has none"
    )
    created_at: datetime

    @classmethod
    def from_row(cls, row: CaptureFrame) -> CaptureFrameOut:
        fix = gps_of(row)
        return cls(
            id=row.id,
            name=row.name,
            position=row.position,
            camera=CameraSchema.from_camera(camera_of(row)),
            gps=GpsSchema.from_fix(fix) if fix is not None else None,
            created_at=row.created_at,
        )


class SessionTransformOut(BaseModel):
    """``map_from_session``: x_map = scale · R(rotation) · x_session + translation."""

    rotation: list[float] = Field(description="unit quaternion [w, x, y, z]")
    translation: list[float]
    scale: float = Field(description="1 for a metric session")
    matrix: list[list[float]] = Field(description="4×4 homogeneous transform, row-major")

    @classmethod
    def from_stored(cls, stored: dict[str, Any]) -> SessionTransformOut:
        similarity = similarity_of(stored)
        matrix = homogeneous(Rigid3d(similarity.rotation, similarity.translation))
        matrix[:3, :3] *= similarity.scale
        return cls(
            rotation=[float(v) for v in stored["rotation"]],
            translation=[float(v) for v in stored["translation"]],
            scale=float(stored["scale"]),
            matrix=np.asarray(matrix).tolist(),
        )


class CheckedFrameOut(BaseModel):
    """A frame localized against the map to align the session."""

    frame: str
    localized: bool
    confidence: float
    position_error_m: float | None = Field(
        description="Distance between where the alignment and the map put it (confident "
        "frames only)"
    )
    rotation_error_deg: float | None
    agrees: bool = Field(description="Within the tolerance and 2°: it took part in the fit")


class StaleReferenceOut(BaseModel):
    image_id: str
    name: str
    reason: str
    retired: bool = Field(False, description="Deleted at once (the map's retire_stale)")


class DriftCorrectionOut(BaseModel):
    median: float
    max: float


class BootstrapGeoRegistrationOut(BaseModel):
    """The geo-registration a session that started an empty map gave it from its frames'
    GPS fixes."""

    set: bool = Field(
        description="The registration was estimated and stored (GET "
        "/v1/maps/{map_id}/geo-registration)"
    )
    reason: str | None = Field(None, description="Why none was set")
    num_references: int | None = Field(None, description="References with GPS")
    num_inliers: int | None = Field(None, description="Of those, the fit's inliers")
    residual_rms_m: float | None = Field(
        None, description="RMS distance between the inliers' centres and their GPS positions"
    )


class CaptureAlignmentOut(BaseModel):
    mode: Literal["aligned", "bootstrap"] = Field(
        description="bootstrap: the map was empty and the session defined its frame"
    )
    map_from_session: SessionTransformOut | None = Field(
        description="null when the session was refused"
    )
    reason: str | None = Field(None, description="Why the session was refused")
    path_length_m: float = Field(description="Length of the session's path (session units)")
    tolerance_m: float | None = Field(
        None, description="max(5 cm, 1 % of the path): how far an agreeing frame may lie"
    )
    confident: int | None = Field(
        None, description="Checked frames localized with confidence ≥ 0.8"
    )
    agreeing: int | None = Field(None, description="Of those, the frames within the tolerance")
    rms_position_m: float | None = Field(None, description="RMS of the agreeing frames' errors")
    rms_rotation_deg: float | None = None
    position_stderr_m: float | None = Field(
        None, description="Standard error of the alignment's position (RMS / √(n − 1))"
    )
    rotation_stderr_deg: float | None = None
    checked: list[CheckedFrameOut]
    stale: list[StaleReferenceOut] = Field(
        default_factory=list,
        description="References the session's frames no longer match, flagged stale",
    )
    drift_correction_m: DriftCorrectionOut | None = Field(
        None,
        description="How far the agreeing frames' centres were moved onto where the map "
        "localized them; the frames between two of them are corrected by interpolation",
    )
    added: int | None = Field(None, description="Frames added as references")
    skipped: int | None = Field(
        None,
        description="Frames not added: beyond the anchors' reach (unanchored), or their "
        "views were in the map already (unless keep_all)",
    )
    unanchored: int | None = Field(
        None,
        description="Frames farther than 5 m along the path from every frame the map "
        "localized: their drift is unmeasured, they are not added",
    )
    spacing_m: float | None = Field(
        None, description="The map's spacing that decided which frames add a view"
    )
    geo_registration: BootstrapGeoRegistrationOut | None = Field(
        None,
        description="bootstrap only, once added: the map's geo-registration estimated from "
        "the frames' GPS fixes (when the map had none and at least 3 frames carry GPS with "
        "height), or why none was set. A session aligned to a map never changes its "
        "registration",
    )


class CaptureProgress(BaseModel):
    done: int = Field(description="Frames checked, then frames added")
    total: int


class CaptureSessionOut(BaseModel):
    id: str
    map_id: str
    name: str
    metric: bool
    keep_all: bool
    state: Literal["open", "queued", "aligning", "adding", "added", "refused", "failed"]
    frames: int = Field(description="Frames uploaded")
    progress: CaptureProgress
    alignment: CaptureAlignmentOut | None = Field(
        description="Set once the session is aligned or refused"
    )
    error: str | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None

    @classmethod
    def from_row(cls, row: CaptureSession) -> CaptureSessionOut:
        result: dict[str, Any] | None = row.result
        alignment = None
        if result is not None:
            values = {k: v for k, v in result.items() if k != "frame_ids"}
            stored = values.pop("map_from_session", None)
            alignment = CaptureAlignmentOut.model_validate(
                values
                | {
                    "map_from_session": (
                        SessionTransformOut.from_stored(stored) if stored is not None else None
                    )
                }
            )
        return cls(
            id=row.id,
            map_id=row.map_id,
            name=row.name,
            metric=row.metric,
            keep_all=row.keep_all,
            state=row.state,
            frames=row.frame_count,
            progress=CaptureProgress(done=row.done, total=row.total),
            alignment=alignment,
            error=row.error,
            created_at=row.created_at,
            started_at=row.started_at,
            finished_at=row.finished_at,
        )


class CaptureSessionPage(BaseModel):
    items: list[CaptureSessionOut] = Field(description="Newest first")
    total: int
    offset: int
    limit: int
