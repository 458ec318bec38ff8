"""Real images the exporters check their ONNX graphs on.

Rendered views of a synthetic scene are always available; frames of the redkitchen dataset
(``../shared/datasets/redkitchen`` beside the repository, or ``$SLLOC_CHECK_DATASET``) are added
when present. Pairs for the matcher checks are frames 10, 20 and 40 apart.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from services.types import UInt8Array
from tools.synthetic.scene import SyntheticScene


def _redkitchen_dir() -> Path | None:
    env = os.environ.get("SLLOC_CHECK_DATASET")
    path = (
        Path(env)
        if env
        else Path(__file__).resolve().parents[2] / ".." / "shared" / "datasets" / "redkitchen"
    )
    return path if (path / "images").is_dir() else None


def _frame(root: Path, index: int) -> UInt8Array | None:
    bgr = cv2.imread(str(root / "images" / f"frame-{index:06d}.color.jpg"), cv2.IMREAD_COLOR)
    return None if bgr is None else np.ascontiguousarray(bgr[:, :, ::-1])


def check_pairs() -> list[tuple[str, UInt8Array, UInt8Array]]:
    """(label, image0, image1) pairs of overlapping RGB uint8 views."""
    views = SyntheticScene(seed=7).views(4, stream=0, prefix="check")
    pairs = [(f"synthetic {a}-{b}", views[a].image, views[b].image) for a, b in ((0, 1), (2, 3))]
    root = _redkitchen_dir()
    if root is not None:
        frames: dict[int, UInt8Array | None] = {}
        for start in (0, 300, 700):
            for gap in (10, 20, 40):
                for i in (start, start + gap):
                    if i not in frames:
                        frames[i] = _frame(root, i)
                a, b = frames[start], frames[start + gap]
                if a is not None and b is not None:
                    pairs.append((f"redkitchen {start}+{gap}", a, b))
    return pairs


def check_images() -> list[UInt8Array]:
    """The distinct images of ``check_pairs``."""
    seen: dict[int, UInt8Array] = {}
    for _, a, b in check_pairs():
        seen.setdefault(id(a), a)
        seen.setdefault(id(b), b)
    return list(seen.values())
