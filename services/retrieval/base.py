"""The global-descriptor contract every retrieval backend fulfils."""

from __future__ import annotations

from typing import Protocol

from services.features.base import LocalFeatures
from services.types import Float32Array, UInt8Array


class GlobalDescriptor(Protocol):
    """Computes one L2-normalised vector per image; cosine similarity ranks references.

    ``name`` is stored with every reference so that descriptors of different backends are
    never compared.
    """

    name: str

    def compute(self, image: UInt8Array, features: LocalFeatures) -> Float32Array:
        """(D,) float32 unit vector of an (H, W, 3) RGB uint8 image and its local features."""
        ...
