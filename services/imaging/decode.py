"""Decoding of uploaded images and depth maps, with size limits checked before decoding."""

from __future__ import annotations

import io
import math
import struct
from dataclasses import dataclass
from tokenize import TokenError

import cv2
import numpy as np
from numpy.lib import format as npy_format

from services.errors import ImageDecodeError, ImageTooLargeError, InvalidInputError
from services.imaging.jpeg_integrity import check_jpeg_complete
from services.types import Float32Array, UInt8Array

# depth beyond this is read as unknown: no sensor or stereo rig measures it, and its squares
# would overflow float32 in the estimators
MAX_DEPTH_M = 1e6
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
# libjpeg decodes at 1/2, 1/4 or 1/8 scale from the DCT coefficients, never holding the full
# image: OpenCV's reduced-colour flags, largest reduction first
_JPEG_REDUCTIONS = (
    (8, cv2.IMREAD_REDUCED_COLOR_8),
    (4, cv2.IMREAD_REDUCED_COLOR_4),
    (2, cv2.IMREAD_REDUCED_COLOR_2),
)


@dataclass(frozen=True)
class DecodedImage:
    """An image decoded at 1/``factor`` of its full size, and that full size (EXIF orientation
    applied). A reduced pixel covers ``factor`` × ``factor`` full pixels, so a COLMAP pixel
    coordinate (top-left pixel centre at (0.5, 0.5)) of ``rgb`` times ``factor`` is the same
    point in the full image."""

    rgb: UInt8Array
    width: int
    height: int
    factor: int = 1


def image_size_from_header(data: bytes) -> tuple[int, int]:
    """(width, height) read from a PNG or JPEG header without decoding the pixels.

    Raises:
        ImageDecodeError: not a PNG or JPEG, or a truncated header.
    """
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24:
        width, height = struct.unpack(">II", data[16:24])
        return int(width), int(height)
    if data[:2] == b"\xff\xd8":
        i = 2
        while i + 9 < len(data):
            if data[i] != 0xFF:
                i += 1
                continue
            marker = data[i + 1]
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7 or marker == 0xFF:
                i += 1 if marker == 0xFF else 2
                continue
            (length,) = struct.unpack(">H", data[i + 2 : i + 4])
            if marker in _JPEG_SOF:
                height, width = struct.unpack(">HH", data[i + 5 : i + 9])
                return int(width), int(height)
            i += 2 + length
        raise ImageDecodeError("truncated JPEG: no frame header found")
    raise ImageDecodeError("not a JPEG or PNG image")


def check_pixel_limit(data: bytes, max_pixels: int) -> tuple[int, int]:
    """(width, height) from the header, before anything else reads the image.

    Raises:
        ImageTooLargeError: more than ``max_pixels`` pixels.
        ImageDecodeError: not a PNG or JPEG, or a truncated header.
    """
    width, height = image_size_from_header(data)
    if width * height > max_pixels:
        raise ImageTooLargeError(
            f"image is {width}×{height} = {width * height} pixels; the limit is {max_pixels}"
        )
    return width, height


def decode_image(data: bytes, max_pixels: int) -> UInt8Array:
    """Decode a JPEG or PNG upload into an (H, W, 3) RGB uint8 array, EXIF orientation applied.

    Raises:
        ImageTooLargeError: more than ``max_pixels`` pixels (checked from the header).
        ImageDecodeError: corrupt or unsupported data.
    """
    return decode_image_reduced(data, max_pixels, min_side=None).rgb


def decode_image_reduced(data: bytes, max_pixels: int, min_side: int | None) -> DecodedImage:
    """Decode a JPEG or PNG upload as ``decode_image`` does, a JPEG at the smallest of 1/8,
    1/4 or 1/2 scale whose longer side is still at least ``min_side`` (None: full size) —
    what an extractor that shrinks images to ``min_side`` needs, at a fraction of the time
    and memory of a full decode.

    Raises:
        ImageTooLargeError: more than ``max_pixels`` pixels (checked from the header).
        ImageDecodeError: corrupt or unsupported data.
    """
    width, height = check_pixel_limit(data, max_pixels)
    if width == 0 or height == 0:
        raise ImageDecodeError("image has zero width or height")
    factor, flags = 1, cv2.IMREAD_COLOR
    if data[:2] == b"\xff\xd8":
        check_jpeg_complete(data)
        if min_side is not None:
            factor, flags = next(
                ((f, flag) for f, flag in _JPEG_REDUCTIONS if max(width, height) >= f * min_side),
                (factor, flags),
            )
    bgr = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
    if bgr is None:
        raise ImageDecodeError("image data is corrupt or truncated")
    w, h = math.ceil(width / factor), math.ceil(height / factor)
    if bgr.shape[:2] == (h, w):
        full = (width, height)
    elif bgr.shape[:2] == (w, h):  # EXIF rotated it by 90°
        full = (height, width)
    else:
        raise ImageDecodeError(
            f"the header says {width}×{height}, the data decodes to "
            f"{bgr.shape[1] * factor}×{bgr.shape[0] * factor}"
        )
    cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB, dst=bgr)  # to RGB in place: no copy
    return DecodedImage(np.asarray(bgr, dtype=np.uint8), *full, factor)


def decode_depth(data: bytes, width: int, height: int, max_pixels: int) -> Float32Array:
    """Decode a depth map: 16-bit PNG in millimetres or ``.npy`` float32 in metres.

    Invalid depth (0, 65535, non-finite, negative, beyond ``MAX_DEPTH_M``) becomes 0. The map
    must match the image size.

    Returns:
        (H, W) float32 depth in metres, 0 where unknown.
    """
    if data[:6] == b"\x93NUMPY":
        depth: Float32Array = _load_npy_depth(data, width, height)
    else:
        w, h = image_size_from_header(data)
        if w * h > max_pixels:
            raise ImageTooLargeError(f"depth map has {w * h} pixels; the limit is {max_pixels}")
        _check_depth_size(w, h, width, height)
        raw = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
            raise InvalidInputError("depth PNG must be single-channel 16-bit (millimetres)")
        depth = raw.astype(np.float32) / 1000.0
        depth[raw == 65535] = 0.0
    _check_depth_size(depth.shape[1], depth.shape[0], width, height)
    depth[~np.isfinite(depth) | (depth < 0) | (depth > MAX_DEPTH_M)] = 0.0
    out: Float32Array = depth
    return out


def _load_npy_depth(data: bytes, width: int, height: int) -> Float32Array:
    """A ``.npy`` depth map as (height, width) float32. Its header (shape, dtype) is checked
    against the image and the upload's length before anything is allocated.

    Raises:
        InvalidInputError: not a 2-D float32/float64 array of the image's size, or a header
            that the data does not match.
    """
    stream = io.BytesIO(data)
    try:
        version = npy_format.read_magic(stream)
        if version == (1, 0):
            shape, _, dtype = npy_format.read_array_header_1_0(stream)
        else:
            shape, _, dtype = npy_format.read_array_header_2_0(stream)
    except (ValueError, SyntaxError, TokenError) as exc:  # numpy parses the header as Python
        raise InvalidInputError(f"depth .npy header could not be read: {exc}") from None
    if len(shape) != 2 or dtype.kind != "f" or dtype.itemsize not in (4, 8):
        raise InvalidInputError(
            f"depth .npy must be a 2-D float32 or float64 array in metres, "
            f"got shape {shape} of {dtype}"
        )
    _check_depth_size(shape[1], shape[0], width, height)
    if len(data) - stream.tell() != height * width * dtype.itemsize:
        raise InvalidInputError("depth .npy data does not match its header")
    stream.seek(0)
    try:
        loaded = npy_format.read_array(stream, allow_pickle=False)
    except ValueError as exc:
        raise InvalidInputError(f"depth .npy could not be read: {exc}") from None
    depth: Float32Array = loaded.astype(np.float32)
    return depth


def _check_depth_size(depth_width: int, depth_height: int, width: int, height: int) -> None:
    if (depth_width, depth_height) != (width, height):
        raise InvalidInputError(
            f"depth map is {depth_width}×{depth_height}, the image is {width}×{height}"
        )
