from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field

from app.schemas.geo import GpsSchema
from app.schemas.geometry import CameraSchema, PoseSchema
from app.schemas.text import Name
from app.usecases.images import NewImage, StoredImage


class ImageMetadata(BaseModel):
    """The ``metadata`` form field of an image upload (a JSON string)."""

    name: Name
    camera: CameraSchema
    cam_from_world: PoseSchema
    gps: GpsSchema | None = Field(
        None, description="Where it was taken; when absent, the image's EXIF GPS if any"
    )

    def to_new_image(self) -> NewImage:
        return NewImage(
            self.name,
            self.camera.to_camera(),
            self.cam_from_world.to_rigid(),
            self.gps.to_fix() if self.gps else None,
        )


class StaleOut(BaseModel):
    since: datetime
    reason: str


class ImageOut(BaseModel):
    id: str
    name: str
    camera: CameraSchema
    cam_from_world: PoseSchema
    num_keypoints: int
    has_depth: bool
    created_at: datetime
    gps: GpsSchema | None = None
    has_original: bool = Field(
        description="Its bytes as uploaded are kept (GET …/original; false for images added "
        "before originals were kept: they serve their stored features but cannot be "
        "described again)"
    )
    original_sha256: str | None = Field(
        None, description="SHA-256 of the original bytes (hex), when kept"
    )
    stale: StaleOut | None = Field(
        None,
        description="Flagged stale: frames of a capture session that cover it no longer "
        "match it (the place changed, or the image is not of it); delete it to retire it",
    )

    @classmethod
    def from_stored(cls, image: StoredImage) -> ImageOut:
        return cls(
            id=image.id,
            name=image.name,
            camera=CameraSchema.from_camera(image.camera),
            cam_from_world=PoseSchema.from_rigid(image.cam_from_world),
            num_keypoints=image.num_keypoints,
            has_depth=image.has_depth,
            created_at=image.created_at,
            gps=GpsSchema.from_fix(image.gps) if image.gps else None,
            has_original=image.has_original,
            original_sha256=image.original_sha256,
            stale=(
                StaleOut(since=image.stale_since, reason=image.stale_reason or "")
                if image.stale_since is not None
                else None
            ),
        )


class ImagePage(BaseModel):
    items: list[ImageOut]
    total: int
    offset: int
    limit: int
