from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field

from app.schemas.geometry import CameraSchema, PoseSchema


class ImageMetadata(BaseModel):
    """The ``metadata`` form field of an image upload (a JSON string)."""

    name: str = Field(min_length=1, max_length=255)
    camera: CameraSchema
    cam_from_world: PoseSchema


class ImageOut(BaseModel):
    id: str
    name: str
    camera: CameraSchema
    cam_from_world: PoseSchema
    num_keypoints: int
    has_depth: bool
    created_at: datetime


class ImagePage(BaseModel):
    items: list[ImageOut]
    total: int
    offset: int
    limit: int
