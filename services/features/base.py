"""The local-feature contract every extractor backend fulfils."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

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


class FeatureExtractor(Protocol):
    """Detects and describes keypoints.

    ``name`` identifies the model and its configuration; it is stored with every reference
    image so that features of different extractors are never matched against each other.
    """

    name: str

    def extract(self, image: UInt8Array) -> LocalFeatures:
        """Features of an (H, W, 3) RGB uint8 image."""
        ...

    def with_budget(self, max_keypoints: int | None, max_side: int | None) -> FeatureExtractor:
        """The same extractor with another keypoint budget and/or longer image side (None
        keeps the current one); shares the heavy parts (model sessions).

        Raises:
            ValueError: a value this extractor cannot honour (the message says why).
        """
        ...
