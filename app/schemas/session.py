"""Query frames with AR-session poses, and the session alignment in the answer.

A session pose is the device's camera-to-session transform as the AR framework reports it:
ARKit ``ARFrame.camera.transform``, ARCore ``Camera.getPose()`` (as a matrix:
``Pose.toMatrix``, column-major there, transpose it), WebXR ``XRViewerPose.transform``;
camera axes x right, y up, z backward (OpenGL); metres.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, Field, field_validator, model_validator

from app.schemas.geometry import CameraSchema, FiniteFloat
from services.errors import InvalidInputError
from services.geometry.rigid import Rigid3d
from services.geometry.session_pose import cam_from_session, homogeneous, rigid_from_matrix

# a schema-level bound, whatever SLLOC_MAX_FRAMES says (the setting is checked per request)
MAX_FRAMES_SCHEMA = 32


class SessionPoseSchema(BaseModel):
    """``session_from_camera`` with OpenGL camera axes (ARKit ``camera.transform``): either
    ``matrix`` or ``position`` with ``orientation``."""

    matrix: list[list[FiniteFloat]] | None = Field(
        None,
        min_length=4,
        max_length=4,
        description="4×4 homogeneous transform, row-major (rows of [R | t], last row "
        "[0, 0, 0, 1]); R must be a rotation. ARKit's simd_float4x4 is column-major: send "
        "its transpose (rows = [columns.0.x, columns.1.x, columns.2.x, columns.3.x], …)",
        examples=[[[1, 0, 0, 0.1], [0, 1, 0, 0.0], [0, 0, 1, -0.2], [0, 0, 0, 1]]],
    )
    position: list[FiniteFloat] | None = Field(
        None, min_length=3, max_length=3, description="camera centre in the session, metres"
    )
    orientation: list[FiniteFloat] | None = Field(
        None,
        min_length=4,
        max_length=4,
        description="unit quaternion [w, x, y, z] of the camera-to-session rotation (ARKit "
        "simd_quatf and Unity list it as x, y, z, w: reorder)",
    )

    @field_validator("matrix")
    @classmethod
    def _rows(cls, rows: list[list[float]] | None) -> list[list[float]] | None:
        if rows is not None and any(len(row) != 4 for row in rows):
            raise ValueError("matrix must be 4×4: four rows of four numbers")
        return rows

    @field_validator("orientation")
    @classmethod
    def _unit(cls, q: list[float] | None) -> list[float] | None:
        if q is not None:
            norm = math.sqrt(sum(v * v for v in q))
            if abs(norm - 1.0) > 1e-3:
                raise ValueError(f"orientation must be a unit quaternion (norm {norm:.6g})")
        return q

    @model_validator(mode="after")
    def _one_form(self) -> SessionPoseSchema:
        by_matrix = self.matrix is not None
        by_parts = self.position is not None or self.orientation is not None
        if by_matrix == by_parts:
            raise ValueError("give either matrix or position with orientation")
        if by_parts and (self.position is None or self.orientation is None):
            raise ValueError("position and orientation go together")
        if by_matrix:
            try:
                rigid_from_matrix(np.array(self.matrix), "matrix")
            except InvalidInputError as exc:
                raise ValueError(str(exc)) from None
        return self

    def to_cam_from_session(self) -> Rigid3d:
        """The engine's ``cam_from_session`` (COLMAP camera axes)."""
        if self.matrix is not None:
            session_from_camera = rigid_from_matrix(np.array(self.matrix), "matrix")
        else:
            session_from_camera = Rigid3d.from_quaternion(
                np.array(self.orientation), np.array(self.position)
            )
        return cam_from_session(session_from_camera)


class FrameIn(BaseModel):
    """One uploaded image's camera and session pose (``params.frames[i]`` goes with the
    i-th ``image`` part)."""

    camera: CameraSchema | None = Field(
        None, description="This frame's intrinsics; default: params.camera, else the default"
    )
    session_pose: SessionPoseSchema


class SessionAlignmentOut(BaseModel):
    """``map_from_session``: x_map = R(rotation) · x_session + translation, metres (the map
    is taken to be metric). An AR app parents map content to an anchor with this transform:
    content at map point X appears at session point ``map_from_session⁻¹ · X``."""

    rotation: list[float] = Field(description="unit quaternion [w, x, y, z]")
    translation: list[float]
    matrix: list[list[float]] = Field(description="4×4 homogeneous transform, row-major")

    @classmethod
    def from_rigid(cls, map_from_session: Rigid3d) -> SessionAlignmentOut:
        return cls(
            rotation=[float(v) for v in map_from_session.quaternion],
            translation=[float(v) for v in map_from_session.translation],
            matrix=homogeneous(map_from_session).tolist(),
        )
