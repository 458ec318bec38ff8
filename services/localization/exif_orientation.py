"""The EXIF orientation tag of a JPEG upload, read from its header without decoding pixels.

OpenCV's decoder applies the orientation (``cv2.IMREAD_COLOR``); the camera adaptation needs
to know which turn it applied, so the tag is read here as well.
"""

from __future__ import annotations

import struct

from services.errors import InvalidInputError

_ORIENTATION_TAG = 0x0112

# EXIF orientation → the clockwise turn that displays the stored pixels upright; the other
# values (2, 4, 5, 7) also mirror the image
ORIENTATION_ROTATION_DEG = {1: 0, 3: 180, 6: 90, 8: 270}
MIRRORED_ORIENTATIONS = (2, 4, 5, 7)


def exif_orientation(data: bytes) -> int | None:
    """The orientation tag (1–8) of a JPEG's EXIF block, None when absent (or not a JPEG)."""
    if data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 4 <= len(data) and data[i] == 0xFF:
        marker = data[i + 1]
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no more metadata
            return None
        (length,) = struct.unpack(">H", data[i + 2 : i + 4])
        segment = data[i + 4 : i + 2 + length]
        if marker == 0xE1 and segment[:6] == b"Exif\x00\x00":
            return _tiff_orientation(segment[6:])
        i += 2 + length
    return None


def _tiff_orientation(tiff: bytes) -> int | None:
    """The orientation entry of the first IFD of a TIFF block; None when absent or corrupt."""
    if len(tiff) < 8 or tiff[:2] not in (b"II", b"MM"):
        return None
    order = "<" if tiff[:2] == b"II" else ">"
    (ifd,) = struct.unpack(order + "I", tiff[4:8])
    if ifd + 2 > len(tiff):
        return None
    (count,) = struct.unpack(order + "H", tiff[ifd : ifd + 2])
    for k in range(count):
        entry = ifd + 2 + 12 * k
        if entry + 12 > len(tiff):
            return None
        tag, kind = struct.unpack(order + "HH", tiff[entry : entry + 4])
        if tag == _ORIENTATION_TAG and kind == 3:  # SHORT
            (value,) = struct.unpack(order + "H", tiff[entry + 8 : entry + 10])
            return int(value) if 1 <= value <= 8 else None
    return None


def orientation_rotation_deg(orientation: int | None) -> int:
    """The clockwise turn the decoder applied for ``orientation`` (None or 1: none).

    Raises:
        InvalidInputError: a mirroring orientation, which no camera rotation explains.
    """
    if orientation in MIRRORED_ORIENTATIONS:
        raise InvalidInputError(
            f"the image's EXIF orientation {orientation} mirrors it, and a mirrored image has "
            "no camera intrinsics: upload it unmirrored (EXIF orientation 1, 3, 6 or 8), or "
            "without camera"
        )
    return ORIENTATION_ROTATION_DEG.get(orientation or 1, 0)
