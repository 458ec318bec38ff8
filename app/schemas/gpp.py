"""The Open AR Cloud GeoPose Protocol (OSCP GPP, version 1) request and response, as OpenVPS
serves them: field names as the protocol spells them. Only what a visual positioning answer
uses is read (the first camera reading and the first geolocation reading); other sensor
readings are accepted and ignored."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field
from pydantic.alias_generators import to_camel

from app.schemas.geo import GeoPoseSchema


class _Lenient(BaseModel):
    """Fields in the protocol's camelCase; fields slloc does not use (privacy, timestamps,
    other sensors' readings…) are ignored."""

    model_config = ConfigDict(extra="ignore", alias_generator=to_camel, populate_by_name=True)


class CameraParam(_Lenient):
    model: str | None = Field(
        None, description="COLMAP model name (UNKNOWN_CAMERA or absent: no intrinsics)"
    )
    model_params: list[float] | None = Field(None, description="COLMAP parameter order")


class ImageOrientation(_Lenient):
    mirrored: bool = False
    rotation: float = 0.0


class CameraReading(_Lenient):
    sequence_number: int = 0
    image_format: str = Field(
        description="JPG, JPEG or PNG (encoded bytes), or RGBA32, RGB24, GRAY8 (raw pixels "
        "of ``size``)"
    )
    size: list[int] = Field(min_length=2, max_length=2, description="width, height")
    image_bytes: str = Field(description="base64")
    image_orientation: ImageOrientation | None = None
    params: CameraParam | None = None


class GeolocationReading(_Lenient):
    latitude: float = Field(ge=-90, le=90, allow_inf_nan=False)
    longitude: float = Field(ge=-180, le=180, allow_inf_nan=False)
    altitude: float | None = Field(None, allow_inf_nan=False)
    accuracy: float | None = Field(None, gt=0, allow_inf_nan=False)


class SensorReadings(_Lenient):
    camera_readings: list[CameraReading] = Field(min_length=1, max_length=1)
    geolocation_readings: list[GeolocationReading] | None = None


class GeoPoseAccuracy(BaseModel):
    position: float = Field(description="metres")
    orientation: float = Field(description="degrees")


class GeoPoseReq(_Lenient):
    id: str = Field(max_length=255)
    timestamp: float | None = None
    type: str = "geopose"
    sensors: list[dict[str, Any]] = Field(default_factory=list, max_length=64)
    sensor_readings: SensorReadings


class GeoPoseResp(BaseModel):
    id: str
    timestamp: float = Field(description="milliseconds since the Unix epoch")
    accuracy: GeoPoseAccuracy
    type: str = "geopose"
    geopose: GeoPoseSchema
