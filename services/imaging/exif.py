"""The EXIF block of a JPEG or PNG upload, parsed by Pillow from the header alone."""

from __future__ import annotations

import io
import struct

from PIL import Image, ImageFile, JpegImagePlugin, PngImagePlugin

# Pillow's format readers, by the magic bytes of the formats an upload may be
_READERS: tuple[tuple[bytes, type[ImageFile.ImageFile]], ...] = (
    (b"\xff\xd8", JpegImagePlugin.JpegImageFile),
    (b"\x89PNG\r\n\x1a\n", PngImagePlugin.PngImageFile),
)


def header_exif(data: bytes) -> Image.Exif:
    """The EXIF of a JPEG (its first APP1 Exif segment) or PNG (an eXIf chunk before the
    pixel data); empty when it has none, an unreadable one, or is neither.

    Pillow's format reader is constructed directly rather than through ``Image.open``: it
    reads the header and metadata only, and leaves the size the header claims unchecked
    (``Image.open`` raises over 2 × ``Image.MAX_IMAGE_PIXELS``, warns over 1 ×); the pixel
    limit is the caller's to enforce. The EXIF block is parsed alone, without ``getexif``:
    a PNG's ``getexif`` decodes the pixels to look for an eXIf chunk after them, and any
    ``getexif`` falls back to an XMP orientation, which OpenCV's decoder does not apply.
    """
    reader = next((r for magic, r in _READERS if data.startswith(magic)), None)
    exif = Image.Exif()
    if reader is None:
        return exif
    try:
        with reader(io.BytesIO(data)) as image:
            raw = image.info.get("exif")
        if isinstance(raw, bytes):
            exif.load(raw)
    except (OSError, SyntaxError, ValueError, EOFError, struct.error):
        return Image.Exif()
    return exif
