"""The local-feature contract every extractor backend fulfils."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from services.runtime.spare_workers import SpareWorkers
from services.types import Float32Array, UInt8Array


@dataclass(frozen=True)
class LocalFeatures:
    """Keypoints of one image.

    Attributes:
        keypoints: (N, 2) float32 pixel coordinates in the original image, COLMAP convention
            (centre of the top-left pixel at (0.5, 0.5)).
        descriptors: (N, D) float32, L2-normalised rows.
        scores: (N,) float32 detection scores (higher is better).
        image_size: (width, height) of the original image; learned matchers normalise
            keypoints by it.
    """

    keypoints: Float32Array
    descriptors: Float32Array
    scores: Float32Array
    image_size: tuple[int, int]

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])

    def at_full_size(self, factor: int, image_size: tuple[int, int]) -> LocalFeatures:
        """These features, found on an image decoded at 1/``factor`` scale, in the pixels of
        the full ``image_size`` image (COLMAP coordinates scale exactly about the corner)."""
        if factor == 1:
            return self
        return LocalFeatures(
            self.keypoints * np.float32(factor), self.descriptors, self.scores, image_size
        )


class FeatureExtractor(Protocol):
    """Detects and describes keypoints.

    ``name`` identifies the model and its configuration; it is stored with every reference
    image so that features of different extractors are never matched against each other.
    """

    name: str
    # the longer side images are shrunk to before detection: a larger image brings nothing
    max_side: int
    # the most keypoints it returns of an image
    max_keypoints: int
    # whether a turned image gives the same keypoints and descriptors, turned (SIFT assigns
    # each keypoint its orientation): a sideways query then matches as well as an upright one
    rotation_invariant: bool

    def extract(self, image: UInt8Array, spare: SpareWorkers | None = None) -> LocalFeatures:
        """Features of an (H, W, 3) RGB uint8 image. ``spare``: idle workers the extraction
        may borrow (extractors that cannot use more threads for one image ignore it)."""
        ...

    def with_budget(self, max_keypoints: int | None, max_side: int | None) -> FeatureExtractor:
        """The same extractor with another keypoint budget and/or longer image side (None
        keeps the current one); shares the heavy parts (model sessions).

        Raises:
            ValueError: a value this extractor cannot honour (the message says why).
        """
        ...
