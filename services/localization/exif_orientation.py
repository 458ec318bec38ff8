"""The EXIF orientation tag of a JPEG or PNG upload, read from its header without decoding
pixels.

OpenCV's decoder applies the orientation (``cv2.IMREAD_COLOR``, a PNG's eXIf chunk too); the
camera adaptation needs to know which turn it applied, so the tag is read here as well.
"""

from __future__ import annotations

from PIL import ExifTags

from services.errors import InvalidInputError
from services.imaging.exif import header_exif

# EXIF orientation → the clockwise turn that displays the stored pixels upright; the other
# values (2, 4, 5, 7) also mirror the image
ORIENTATION_ROTATION_DEG = {1: 0, 3: 180, 6: 90, 8: 270}
MIRRORED_ORIENTATIONS = (2, 4, 5, 7)


def exif_orientation(data: bytes) -> int | None:
    """The orientation tag (1–8) of a JPEG's or PNG's EXIF, None when absent or invalid (or
    neither format)."""
    value = header_exif(data).get(ExifTags.Base.Orientation)
    return value if isinstance(value, int) and 1 <= value <= 8 else None


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
