"""Cameras and poses as they cross the API (COLMAP models; ``cam_from_world``, [w, x, y, z])."""

from __future__ import annotations

import math
from typing import Annotated, Literal, cast

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from services.errors import InvalidInputError
from services.geometry.camera import (
    CAMERA_MODELS,
    FOCAL_RANGE,
    MAX_DISTORTION,
    Camera,
    check_plausible,
)
from services.geometry.rigid import MAX_TRANSLATION_M, Rigid3d, pose_problem

# numbers as JSON numbers: strict, so that a string ("500") or a boolean is refused
FiniteFloat = Annotated[float, Field(strict=True, allow_inf_nan=False)]
# services.geometry.camera.CAMERA_MODELS (a test checks they agree)
CameraModelName = Literal[
    "SIMPLE_PINHOLE",
    "PINHOLE",
    "SIMPLE_RADIAL",
    "RADIAL",
    "OPENCV",
    "OPENCV_FISHEYE",
    "FULL_OPENCV",
    "FOV",
    "SIMPLE_RADIAL_FISHEYE",
    "RADIAL_FISHEYE",
    "THIN_PRISM_FISHEYE",
    "RAD_TAN_THIN_PRISM_FISHEYE",
]


class CameraSchema(BaseModel):
    """A COLMAP camera. Pixel coordinates use COLMAP's convention: the centre of the top-left
    pixel is (0.5, 0.5), so an ideal principal point of a W×H image is (W/2, H/2)."""

    model_config = ConfigDict(
        json_schema_extra={
            "example": {
                "model": "PINHOLE",
                "width": 640,
                "height": 480,
                "params": [525.0, 525.0, 320.0, 240.0],
            },
            # each model's number of parameters
            "allOf": [
                {
                    "if": {"properties": {"model": {"const": model}}},
                    "then": {
                        "properties": {"params": {"minItems": len(names), "maxItems": len(names)}}
                    },
                }
                for model, names in CAMERA_MODELS.items()
            ],
        }
    )

    model: CameraModelName
    width: int = Field(gt=0, le=100_000)
    height: int = Field(gt=0, le=100_000)
    params: list[FiniteFloat] = Field(
        description="COLMAP order: "
        + "; ".join(f"{model}: {', '.join(names)}" for model, names in CAMERA_MODELS.items())
        + f". Plausible: focal lengths {FOCAL_RANGE[0]:g}–{FOCAL_RANGE[1]:g} × the longer "
        "image side, the principal point within the image extended by its size, distortion "
        f"within ±{MAX_DISTORTION:g}"
    )

    @model_validator(mode="after")
    def _check(self) -> CameraSchema:
        """The model's parameter count, then physical plausibility (``check_plausible``)."""
        try:
            check_plausible(self.to_camera())
        except InvalidInputError as exc:
            raise ValueError(str(exc)) from None
        return self

    def to_camera(self) -> Camera:
        return Camera(self.model, self.width, self.height, tuple(self.params))

    @classmethod
    def from_camera(cls, camera: Camera) -> CameraSchema:
        """A stored camera as it was accepted (not checked again: the plausible range may
        have narrowed since)."""
        return cls.model_construct(
            model=cast(CameraModelName, camera.model),
            width=camera.width,
            height=camera.height,
            params=list(camera.params),
        )


class PoseSchema(BaseModel):
    """``cam_from_world``: x_cam = R(rotation) · x_world + translation."""

    rotation: list[FiniteFloat] = Field(
        min_length=4, max_length=4, description="unit quaternion [w, x, y, z]"
    )
    translation: list[FiniteFloat] = Field(
        min_length=3,
        max_length=3,
        description=f"metres (map units); on input |translation| (the camera centre's "
        f"distance from the map's origin) at most {MAX_TRANSLATION_M:g}",
    )

    @field_validator("rotation")
    @classmethod
    def _unit(cls, q: list[float]) -> list[float]:
        norm = math.sqrt(sum(v * v for v in q))
        if abs(norm - 1.0) > 1e-3:
            raise ValueError(f"rotation must be a unit quaternion (norm {norm:.6g})")
        return q

    @model_validator(mode="after")
    def _physical(self) -> PoseSchema:
        problem = pose_problem(np.array(self.rotation), np.array(self.translation))
        if problem is not None:
            raise ValueError(problem)
        return self

    def to_rigid(self) -> Rigid3d:
        return Rigid3d.from_quaternion(np.array(self.rotation), np.array(self.translation))

    @classmethod
    def from_rigid(cls, pose: Rigid3d) -> PoseSchema:
        """A pose as the service answers it (not checked: an estimate or a stored pose is
        answered as it is)."""
        return cls.model_construct(
            rotation=[float(v) for v in pose.quaternion],
            translation=[float(v) for v in pose.translation],
        )
