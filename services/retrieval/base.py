"""The global-descriptor contract every retrieval backend fulfils."""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from services.features.base import LocalFeatures


class GlobalDescriptor(Protocol):
    """Computes one L2-normalised vector per image; cosine similarity ranks references.

    ``name`` is stored with every reference so that descriptors of different backends are
    never compared.
    """

    name: str

    def compute(self, image: NDArray[np.uint8], features: LocalFeatures) -> NDArray[np.float32]:
        """(D,) float32 unit vector of an (H, W, 3) RGB uint8 image and its local features."""
        ...
