"""The Open AR Cloud GeoPose Protocol's request as a localize request (its image, intrinsics,
GPS fix and prior pose), the version its answer is given in, and the answer itself.

The route reads the protocol's JSON (``app/schemas/gpp.py``) into a ``GppQuery`` and writes the
answer from ``GeoPose`` and ``GppAccuracy``: nothing here knows the HTTP schema."""

from __future__ import annotations

import base64
import binascii
import io
import math
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from app.usecases.localize import LocalizeRequest
from services.errors import InvalidInputError
from services.geo.geopose import GeoPose, GeoPoseAccuracy
from services.geo.gps import GpsFix
from services.geometry.camera import CAMERA_MODELS, Camera, check_plausible
from services.types import FloatArray

ENCODED_FORMATS = {"JPG", "JPEG", "PNG"}
# raw pixel formats: channels and the OpenCV conversion to BGR
RAW_FORMATS = {
    "RGBA32": (4, cv2.COLOR_RGBA2BGR),
    "RGB24": (3, cv2.COLOR_RGB2BGR),
    "GRAY8": (1, cv2.COLOR_GRAY2BGR),
}
_SIGNATURES = (b"\xff\xd8\xff", b"\x89PNG\r\n\x1a\n")  # JPEG, PNG
_NO_INTRINSICS = (None, "", "UNKNOWN_CAMERA", "UNKNOWN")

CameraAxes = Literal["forward_left_up", "opengl"]
# the forward-left-up camera's axes (x forward, y left, z up) in the OpenGL camera frame
# (x right, y up, z backward): a rotation of 120° about (−1, 1, 1)/√3, quaternion
# (x, y, z, w) = (−½, ½, ½, ½)
GL_FROM_FLU = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])

OSCP_MEDIA_TYPE = "application/vnd.oscp+json"
VERSIONS = ("1.0", "2.0")


@dataclass(frozen=True)
class GppReading:
    """A camera reading: ``image_bytes`` base64 (or a data URL), ``image_format`` as the
    client labels it, ``size`` (width, height) in pixels when given, and the image's
    orientation (``rotation_deg`` degrees, ``mirrored``)."""

    image_bytes: str
    image_format: str | None = None
    size: tuple[int, int] | None = None
    mirrored: bool = False
    rotation_deg: float = 0.0


@dataclass(frozen=True)
class GppIntrinsics:
    """A camera's intrinsics as the protocol gives them: a COLMAP model name (None, ``""``,
    ``UNKNOWN_CAMERA`` or ``UNKNOWN``: none) and its parameters in COLMAP's order."""

    model: str | None
    model_params: tuple[float, ...] | None


@dataclass(frozen=True)
class GppQuery:
    """What a GeoPose request asks: its first camera reading (with the intrinsics its sensor
    may carry instead), its position hint and the version of its shape (1 or 2)."""

    reading: GppReading
    params: GppIntrinsics | None
    hint: GpsFix | None
    version: int


@dataclass(frozen=True)
class GppAccuracy:
    """The answer's accuracy as the protocol gives it: ``position_m`` the mean of the three
    axes' 1-σ (metres), ``orientation_deg`` the mean of the three angles' 1-σ (degrees)."""

    position_m: float
    orientation_deg: float


def check_orientation(reading: GppReading) -> None:
    """Raises:
    InvalidInputError: a mirrored or rotated image (not served: it would be localized as
        another camera's).
    """
    if reading.mirrored or reading.rotation_deg % 360.0 != 0.0:
        raise InvalidInputError(
            f"cameraReadings[0].imageOrientation (mirrored {reading.mirrored}, rotation "
            f"{reading.rotation_deg:g}) is not supported: send the image upright as the camera "
            "took it (mirrored false, rotation 0)"
        )


def image_bytes(reading: GppReading, max_pixels: int) -> tuple[bytes, tuple[int, int]]:
    """The reading's image as JPEG/PNG bytes (raw pixels are encoded as PNG), and its width
    and height. JPEG and PNG bytes are recognised by their signature whatever
    ``imageFormat`` says; raw pixels are read only when labelled so with ``size`` and their
    byte count fits it.

    Raises:
        InvalidInputError: bad base64, an unknown format, or raw data of the wrong size.
    """
    encoded = reading.image_bytes
    if encoded.startswith("data:") and "," in encoded[:100]:  # a data URL as it is
        encoded = encoded.split(",", 1)[1]
    try:
        data = base64.b64decode(encoded, validate=True)
    except (binascii.Error, ValueError):
        raise InvalidInputError("cameraReadings[0].imageBytes is not valid base64") from None
    fmt = (reading.image_format or "").upper()
    if data.startswith(_SIGNATURES):
        return data, _encoded_size(data)
    if fmt in ENCODED_FORMATS:
        raise InvalidInputError(
            f"cameraReadings[0]: imageFormat {fmt} but the bytes are neither JPEG nor PNG"
        )
    if fmt not in RAW_FORMATS:
        known = ", ".join(sorted(ENCODED_FORMATS | set(RAW_FORMATS)))
        raise InvalidInputError(
            f"cameraReadings[0].imageFormat {reading.image_format!r} and the bytes are neither "
            f"JPEG nor PNG: known are {known}"
        )
    if reading.size is None:
        raise InvalidInputError(f"cameraReadings[0].size is needed for raw {fmt} pixels")
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
    return bytes(png), (width, height)


def _encoded_size(data: bytes) -> tuple[int, int]:
    """Width and height from a JPEG's or PNG's header (nothing is decoded)."""
    try:
        with Image.open(io.BytesIO(data)) as image:
            width, height = image.size
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError):
        raise InvalidInputError("cameraReadings[0]: the JPEG/PNG image is unreadable") from None
    return int(width), int(height)


def camera(query: GppQuery, size: tuple[int, int]) -> Camera | None:
    """The reading's intrinsics (None: unknown camera) for an image of ``size`` (the
    reading's ``size`` when it gives one).

    Raises:
        InvalidInputError: a model slloc does not know, or the wrong number of parameters.
    """
    params = query.params
    if params is None or params.model in _NO_INTRINSICS or not params.model_params:
        return None
    if params.model not in CAMERA_MODELS:
        raise InvalidInputError(
            f"cameraReadings[0].params.model {params.model!r}: known are "
            f"{', '.join(CAMERA_MODELS)} and UNKNOWN_CAMERA"
        )
    width, height = query.reading.size or size
    cam = Camera(params.model, width, height, tuple(params.model_params))
    check_plausible(cam)
    return cam


def localize_request(query: GppQuery, size: tuple[int, int]) -> LocalizeRequest:
    return LocalizeRequest(camera=camera(query, size))


def answer_version(accept: str | None, request_version: int) -> tuple[str, str] | None:
    """The protocol version and media type to answer in for the ``Accept`` header, None when
    it accepts nothing served. ``application/vnd.oscp+json; version=1.0`` (or 2.0) is
    answered in that version under that media type; JSON or anything else acceptable in the
    request's own version as ``application/json``."""
    default = (f"{request_version}.0", "application/json")
    if not accept or not accept.strip():
        return default
    ranges = []
    for order, item in enumerate(accept.split(",")):
        media, *raw = (part.strip() for part in item.split(";"))
        params = {}
        for p in raw:
            key, _, value = p.partition("=")
            if key:
                params[key.strip().lower()] = value.strip().strip('"')
        try:
            q = float(params.get("q", "1"))
        except ValueError:
            q = 1.0
        if q > 0 and math.isfinite(q):
            ranges.append((-q, order, media.lower(), params))
    for _, _, media, params in sorted(ranges):
        if media == OSCP_MEDIA_TYPE:
            version = params.get("version", f"{request_version}.0")
            version = f"{version}.0" if version.isdigit() else version
            if version in VERSIONS:
                return version, f"{OSCP_MEDIA_TYPE}; version={version}"
        elif media in ("application/json", "application/*", "*/*"):
            return default
    return None


def answer_rotation(pose: GeoPose, axes: CameraAxes) -> FloatArray:
    """ENU-from-camera rotation of the answer in the camera axes asked for."""
    enu_from_gl: FloatArray = np.asarray(pose.enu_from_camera, np.float64)
    return enu_from_gl if axes == "opengl" else enu_from_gl @ GL_FROM_FLU


def answer_accuracy(accuracy: GeoPoseAccuracy) -> GppAccuracy:
    """The protocol's means over all components: the three axes' 1-σ (horizontal_m is the
    2-D RMS of East and North, each horizontal_m/√2) and the three angles' (the pose's RMS
    rotation angle spread evenly over them: 1/√3 each)."""
    position = (math.sqrt(2.0) * accuracy.horizontal_m + accuracy.vertical_m) / 3.0
    return GppAccuracy(position, accuracy.yaw_deg / math.sqrt(3.0))
