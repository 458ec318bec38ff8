"""Weight-free global descriptor: a blurred, zero-mean grey thumbnail (a "tiny image").

Cheap and good enough for sequential captures; it is not invariant to large viewpoint
changes. Measured on redkitchen (100 references, 50 queries): 27 of the 32 queries that have
a reference within 0.5 m and 30° find one in the top 10.
"""

from __future__ import annotations

import cv2
import numpy as np

from services.features.base import LocalFeatures
from services.types import Float32Array, UInt8Array

_BLUR_WIDTH = 640


class ThumbnailDescriptor:
    def __init__(self, width: int = 32, height: int = 24, blur_sigma: float = 4.0) -> None:
        self.size = (width, height)
        self.blur_sigma = blur_sigma
        self.name = f"thumbnail-{width}x{height}-s{blur_sigma:g}"

    def compute(self, image: UInt8Array, features: LocalFeatures) -> Float32Array:
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        height, width = gray.shape
        if width > _BLUR_WIDTH:
            # the blur is relative to a 640-pixel-wide image (so the descriptor does not depend
            # on resolution): a larger image is first averaged down to that width, as blurring
            # it in full (a kernel of hundreds of pixels) costs seconds for nothing
            size = (_BLUR_WIDTH, max(1, round(height * _BLUR_WIDTH / width)))
            gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
        gray = gray.astype(np.float32)
        sigma = self.blur_sigma * gray.shape[1] / _BLUR_WIDTH
        thumb = cv2.resize(
            cv2.GaussianBlur(gray, (0, 0), sigma), self.size, interpolation=cv2.INTER_AREA
        ).ravel()
        thumb -= thumb.mean()
        norm = float(np.linalg.norm(thumb))
        return (thumb / norm if norm > 0 else thumb).astype(np.float32)
