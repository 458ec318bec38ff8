"""What an AR client adds to a localize request and gets back: camera rotation, gravity,
pose conventions (the docs' AR page, "Integrating an AR app")."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, Field

from app.schemas.geometry import CameraSchema, FiniteFloat
from services.geometry.intrinsics_adaptation import CameraAdaptation, rotated_from_camera
from services.geometry.pose_conventions import world_from_cam
from services.geometry.rigid import Rigid3d, matrix_to_quaternion
from services.localization.query_frame import DEFAULT_GRAVITY_MAX_ANGLE_DEG, GravityHint

PoseConvention = Literal["colmap", "opengl", "unity"]


class GravityIn(BaseModel):
    """Measured gravity of the query frame."""

    down: list[FiniteFloat] = Field(
        min_length=3,
        max_length=3,
        description="Direction of gravity (pointing to the earth, any length) in the frame of "
        "`camera` (of the upload when `camera` is absent), COLMAP axes: x right, y down, "
        "z forward. A level landscape camera has [0, 1, 0].",
    )
    max_angle_deg: float = Field(
        DEFAULT_GRAVITY_MAX_ANGLE_DEG,
        gt=0,
        le=180,
        allow_inf_nan=False,
        description="A pose whose gravity is further off is answered localized: false, "
        "reason gravity_mismatch",
    )
    map_down: list[FiniteFloat] | None = Field(
        None,
        min_length=3,
        max_length=3,
        description="The map's down in world coordinates; default: the retrieved "
        "references' mean image down (references captured roughly upright)",
    )

    def to_hint(self) -> GravityHint:
        return GravityHint(
            np.array(self.down),
            self.max_angle_deg,
            np.array(self.map_down) if self.map_down is not None else None,
        )


class OutputIn(BaseModel):
    frames: list[PoseConvention] = Field(
        default_factory=list,
        max_length=3,
        description="Also answer world_from_cam in these conventions (the docs' AR page, "
        "'Pose conventions')",
    )
    pose_of: Literal["upload", "camera"] = Field(
        "upload",
        description="Whose world_from_cam: the uploaded image's camera, or the camera of "
        "`camera` before camera_adaptation's turn (the frame of ARKit's camera.transform "
        "and ARCore's Camera.getPose, which give landscape sensor intrinsics)",
    )

    def camera_pose(self, cam_from_world: Rigid3d, adaptation: CameraAdaptation | None) -> Rigid3d:
        """``cam_from_world`` of the upload → that of the camera ``pose_of`` names."""
        if self.pose_of == "upload" or adaptation is None:
            return cam_from_world
        camera_from_upload = rotated_from_camera(adaptation.rotation_deg).T
        return Rigid3d(
            camera_from_upload @ cam_from_world.rotation,
            camera_from_upload @ cam_from_world.translation,
        )


class CameraAdaptationOut(BaseModel):
    """How the request's camera was adapted to the upload."""

    scale: float = Field(description="Upload pixels per camera pixel (mean of x and y)")
    rotation_deg: int = Field(
        description="Clockwise quarter turn from the camera's image to the upload"
    )
    exif_orientation: int | None = Field(description="The upload's EXIF orientation tag")
    camera: CameraSchema = Field(description="The upload's intrinsics, as used")

    @classmethod
    def from_adaptation(cls, adaptation: CameraAdaptation) -> CameraAdaptationOut:
        sx, sy = adaptation.scale
        return cls(
            scale=(sx + sy) / 2.0,
            rotation_deg=adaptation.rotation_deg,
            exif_orientation=adaptation.exif_orientation,
            camera=CameraSchema.from_camera(adaptation.camera),
        )


class FramePoseOut(BaseModel):
    """Camera-to-world in one convention."""

    matrix: list[list[float]] = Field(
        description="4×4 world_from_cam, row-major, column vectors: x_world = M · x_cam"
    )
    position: list[float] = Field(description="Camera position in the world")
    rotation: list[float] = Field(description="Unit quaternion [w, x, y, z] of M's rotation")

    @classmethod
    def from_pose(cls, cam_from_world: Rigid3d, convention: str) -> FramePoseOut:
        matrix = world_from_cam(cam_from_world, convention)
        return cls(
            matrix=matrix.tolist(),
            position=[float(v) for v in matrix[:3, 3]],
            rotation=[float(v) for v in matrix_to_quaternion(matrix[:3, :3])],
        )
