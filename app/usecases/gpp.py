"""The Open AR Cloud GeoPose Protocol's request as a localize request: its image, intrinsics
and GPS fix."""

from __future__ import annotations

import base64
import binascii

import cv2
import numpy as np

from app.schemas.gpp import CameraReading, GeoPoseReq
from app.usecases.localize import LocalizeRequest
from services.errors import InvalidInputError
from services.geo.gps import GpsFix
from services.geometry.camera import CAMERA_MODELS, Camera, check_plausible

ENCODED_FORMATS = {"JPG", "JPEG", "PNG"}
# raw pixel formats: channels and the OpenCV conversion to BGR
RAW_FORMATS = {
    "RGBA32": (4, cv2.COLOR_RGBA2BGR),
    "RGB24": (3, cv2.COLOR_RGB2BGR),
    "GRAY8": (1, cv2.COLOR_GRAY2BGR),
}


def image_bytes(reading: CameraReading, max_pixels: int) -> bytes:
    """The reading's image as JPEG/PNG bytes (raw pixels are encoded as PNG).

    Raises:
        InvalidInputError: bad base64, an unknown format, or raw data of the wrong size.
    """
    try:
        data = base64.b64decode(reading.image_bytes, validate=True)
    except (binascii.Error, ValueError):
        raise InvalidInputError("cameraReadings[0].imageBytes is not valid base64") from None
    fmt = reading.image_format.upper()
    if fmt in ENCODED_FORMATS:
        return data
    if fmt not in RAW_FORMATS:
        known = ", ".join(sorted(ENCODED_FORMATS | set(RAW_FORMATS)))
        raise InvalidInputError(f"cameraReadings[0].imageFormat {fmt!r}: known are {known}")
    width, height = reading.size
    if width <= 0 or height <= 0 or width * height > max_pixels:
        raise InvalidInputError(f"cameraReadings[0].size {width}×{height} is not acceptable")
    channels, conversion = RAW_FORMATS[fmt]
    if len(data) != width * height * channels:
        raise InvalidInputError(
            f"cameraReadings[0]: {len(data)} bytes for a {width}×{height} {fmt} image "
            f"(expected {width * height * channels})"
        )
    pixels = np.frombuffer(data, np.uint8).reshape(height, width, channels)
    ok, png = cv2.imencode(".png", cv2.cvtColor(pixels, conversion))
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
        raise InvalidInputError("cameraReadings[0]: the image could not be encoded")
    return bytes(png)


def camera(reading: CameraReading) -> Camera | None:
    """The reading's intrinsics (None: unknown camera).

    Raises:
        InvalidInputError: a model slloc does not know, or the wrong number of parameters.
    """
    params = reading.params
    if params is None or params.model in (None, "UNKNOWN_CAMERA") or not params.model_params:
        return None
    if params.model not in CAMERA_MODELS:
        raise InvalidInputError(
            f"cameraReadings[0].params.model {params.model!r}: known are "
            f"{', '.join(CAMERA_MODELS)} and UNKNOWN_CAMERA"
        )
    width, height = reading.size
    cam = Camera(params.model, width, height, tuple(params.model_params))
    check_plausible(cam)
    return cam


def localize_request(body: GeoPoseReq) -> tuple[LocalizeRequest, GpsFix | None]:
    """The localize request of a GeoPose request, and its GPS fix if it has one."""
    reading = body.sensor_readings.camera_readings[0]
    fixes = body.sensor_readings.geolocation_readings or []
    gps = None
    if fixes:
        fix = fixes[0]
        gps = GpsFix(fix.latitude, fix.longitude, fix.altitude, fix.accuracy)
    return LocalizeRequest(camera=camera(reading)), gps
