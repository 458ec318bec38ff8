"""Reading a dataset image as the engine takes it."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from services.types import UInt8Array


def load_rgb(path: Path) -> UInt8Array:
    """The image at ``path`` as an (H, W, 3) RGB array.

    Raises:
        OSError: OpenCV cannot read it.
    """
    bgr = cv2.imread(str(path))
    if bgr is None:
        raise OSError(f"cannot read {path}")
    return np.ascontiguousarray(bgr[:, :, ::-1])
