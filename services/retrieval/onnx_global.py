"""A global-descriptor model given by file path (``SLLOC_GLOBAL_MODEL``), run by onnxruntime.

Input/output contract (checked when the model is loaded):

- one input: float32 ``(1, 3, H, W)``, RGB, values ``(x / 255 − mean) / std`` with ImageNet's
  mean (0.485, 0.456, 0.406) and std (0.229, 0.224, 0.225). ``H`` and ``W`` may be fixed in
  the graph (the image is resized to them, aspect ratio not kept) or symbolic (the image is
  resized so that its longer side is ``max_side``, 512 by default);
- first output: float32 ``(1, D)`` or ``(D,)``; it is L2-normalised here, so any scale works.

EigenPlaces, NetVLAD, MixVPR or CosPlace exports satisfy it as exported by their authors'
code. The descriptor's name is ``onnx-<file stem>-<sha256 prefix>``, so references described by
another model (or another version of the file) are never compared with it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from services.features.base import LocalFeatures
from services.runtime.manifest import file_sha256
from services.types import Float32Array, UInt8Array

_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
_STD = np.array([0.229, 0.224, 0.225], np.float32)


class OnnxGlobalDescriptor:
    def __init__(self, session: Any, path: Path, max_side: int = 512) -> None:
        inputs, outputs = session.get_inputs(), session.get_outputs()
        if len(inputs) != 1 or len(inputs[0].shape) != 4 or inputs[0].shape[1] not in (3, "3"):
            raise ValueError(
                f"{path.name}: a global-descriptor model takes one (1, 3, H, W) input, "
                f"got {[(i.name, i.shape) for i in inputs]}"
            )
        if not outputs:
            raise ValueError(f"{path.name}: the model has no output")
        self.session = session
        self.input_name = inputs[0].name
        height, width = inputs[0].shape[2:]
        self.fixed_size = (
            (int(width), int(height))
            if isinstance(height, int) and isinstance(width, int)
            else None
        )
        self.max_side = max_side
        self.name = f"onnx-{path.stem}-{file_sha256(path)[:12]}"

    def compute(self, image: UInt8Array, features: LocalFeatures) -> Float32Array:
        height, width = image.shape[:2]
        if self.fixed_size is not None:
            size = self.fixed_size
        else:
            scale = self.max_side / max(height, width)
            size = (max(1, round(width * scale)), max(1, round(height * scale)))
        resized = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        tensor = ((resized.astype(np.float32) / 255.0 - _MEAN) / _STD).transpose(2, 0, 1)[None]
        (output,) = self.session.run(None, {self.input_name: np.ascontiguousarray(tensor)})[:1]
        vector = np.asarray(output, np.float32).reshape(-1)
        if not np.isfinite(vector).all():
            raise ValueError(f"{self.name} returned a non-finite descriptor")
        norm = float(np.linalg.norm(vector))
        return vector / norm if norm > 0 else vector
