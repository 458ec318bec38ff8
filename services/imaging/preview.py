"""JPEG previews of reference images: kept for display (the map viewer), never read by the
engine."""

from __future__ import annotations

from dataclasses import dataclass

import cv2

from services.types import UInt8Array

JPEG_QUALITY = 85


@dataclass(frozen=True)
class Preview:
    """A JPEG of ``width`` × ``height`` pixels. A pixel coordinate ``x`` of the full image is
    ``x · width / full_width`` in the preview (both in the COLMAP convention, where the centre
    of the top-left pixel is (0.5, 0.5))."""

    jpeg: bytes
    width: int
    height: int


def make_preview(image: UInt8Array, max_side: int) -> Preview:
    """The JPEG of ``image`` ((H, W, 3) RGB uint8), shrunk so that its longer side is at most
    ``max_side`` pixels (never enlarged)."""
    if max_side <= 0:
        raise ValueError(f"max_side must be positive, got {max_side}")
    height, width = image.shape[:2]
    scale = min(1.0, max_side / max(height, width))
    bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    if scale < 1.0:
        size = (max(1, round(width * scale)), max(1, round(height * scale)))
        bgr = cv2.resize(bgr, size, interpolation=cv2.INTER_AREA)
    ok, encoded = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:  # pragma: no cover - OpenCV encodes any 8-bit RGB image
        raise RuntimeError("JPEG encoding failed")
    return Preview(encoded.tobytes(), int(bgr.shape[1]), int(bgr.shape[0]))
