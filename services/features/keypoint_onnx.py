"""Learned local features (ALIKED, DISK, XFeat) from their exported ONNX graphs
(``slloc models build``).

Every extractor graph takes an (1, 3, H, W) float32 RGB image in [0, 1] and returns its
exported budget of keypoints best first: ``keypoints`` (K, 2) pixels with pixel centres at
integers, ``scores`` (K,), ``descriptors`` (K, D) unit rows; rows with a non-finite score are
padding (DISK finds fewer detections than K on a bland image) and are dropped.
"""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from services.errors import InvalidInputError
from services.features.base import LocalFeatures
from services.runtime.spare_workers import SpareWorkers
from services.types import UInt8Array

MIN_SIDE = 64  # the graph's smallest input side (and enough candidates for its top-k)


@dataclass(frozen=True)
class ResizeOptions:
    """max_keypoints: keypoint budget (at most the exported graph's); max_side: the longer
    image side the image is resized to before detection (never enlarged)."""

    max_keypoints: int = 2048
    max_side: int = 640


class OnnxKeypointExtractor:
    """Runs a keypoint graph (the module docstring's contract); a smaller budget takes a
    prefix of its output. ``side_multiple``: the resized sides are rounded down to multiples
    of it (XFeat's graph resizes its input to multiples of 32 otherwise: one resampling
    instead of two). ``wide_session``: the same graph with the threads of every localize
    worker, run when the idle workers are lent to the extraction (XFeat at 640×480: 28 ms
    on two threads against 41 ms on one)."""

    rotation_invariant = False  # the networks describe keypoints as they were trained: upright

    def __init__(
        self,
        session: Any,
        model_name: str,
        exported_budget: int,
        options: ResizeOptions,
        side_multiple: int = 1,
        wide_session: Any | None = None,
    ) -> None:
        if not 0 < options.max_keypoints <= exported_budget:
            raise ValueError(
                f"max_keypoints must be in 1…{exported_budget} (the exported budget of "
                f"{model_name}), got {options.max_keypoints}"
            )
        if options.max_side < MIN_SIDE:
            raise ValueError(f"max_side must be at least {MIN_SIDE}, got {options.max_side}")
        if side_multiple < 1:
            raise ValueError(f"side_multiple must be >= 1, got {side_multiple}")
        self.session = session
        self.wide_session = wide_session
        self.side_multiple = side_multiple
        self.model_name = model_name
        self.max_side = options.max_side
        self.max_keypoints = options.max_keypoints
        self.exported_budget = exported_budget
        self.options = options
        self.name = f"{model_name}-{options.max_keypoints}-{options.max_side}"

    def with_budget(self, max_keypoints: int | None, max_side: int | None) -> OnnxKeypointExtractor:
        if max_keypoints is None and max_side is None:
            return self
        options = ResizeOptions(
            max_keypoints or self.options.max_keypoints, max_side or self.options.max_side
        )
        return OnnxKeypointExtractor(
            self.session,
            self.model_name,
            self.exported_budget,
            options,
            self.side_multiple,
            self.wide_session,
        )

    def extract(self, image: UInt8Array, spare: SpareWorkers | None = None) -> LocalFeatures:
        height, width = image.shape[:2]
        scale = min(1.0, self.options.max_side / max(height, width))
        new_w, new_h = round(width * scale), round(height * scale)
        step = self.side_multiple
        new_w, new_h = new_w // step * step, new_h // step * step
        if min(new_w, new_h) < MIN_SIDE:
            raise InvalidInputError(
                f"image is too small for {self.model_name}: {width}×{height} resized to "
                f"{new_w}×{new_h}, needs at least {MIN_SIDE} px a side"
            )
        resized = (
            cv2.resize(image, (new_w, new_h), interpolation=cv2.INTER_AREA)
            if (new_w, new_h) != (width, height)
            else image
        )
        tensor = resized.transpose(2, 0, 1)[None].astype(np.float32) / np.float32(255.0)
        lend = spare.borrow_all() if spare is not None and self.wide_session is not None else None
        with lend or nullcontext(False) as wide:
            session: Any = self.wide_session if wide else self.session
            keypoints, scores, descriptors = session.run(None, {"image": tensor})
        n = self.options.max_keypoints
        keep = np.isfinite(scores[:n])
        # graph pixels have centres at integers; COLMAP's at +0.5, where scaling about the
        # image corner is exact
        xy = (keypoints[:n][keep] + 0.5) * np.array([width / new_w, height / new_h], np.float32)
        return LocalFeatures(
            np.ascontiguousarray(xy, dtype=np.float32),
            np.ascontiguousarray(descriptors[:n][keep], dtype=np.float32),
            np.ascontiguousarray(scores[:n][keep], dtype=np.float32),
            (width, height),
        )
