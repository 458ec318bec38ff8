"""A map's retrieval index as the engine searches it, and the VLAD vocabulary it may use."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from services.retrieval.vlad import Vocabulary


@dataclass(frozen=True)
class VocabularyState:
    """A map's published VLAD vocabulary: its version and the map size it was trained at."""

    version: int
    vocabulary: Vocabulary
    trained_images: int


@dataclass(frozen=True)
class RetrievalIndex:
    """Global descriptors of a map's reference images.

    Attributes:
        image_ids: N ids.
        descriptors: (N, D) float32 unit rows.
        centers: (N, 3) float64 camera centres.
        vocabulary: with VLAD retrieval, the map's vocabulary (``descriptors`` are VLAD
            vectors; the query is encoded with it); None: the localizer's global descriptor.
        vocabulary_version: its version (0 without one).
    """

    image_ids: list[str]
    descriptors: NDArray[np.float32]
    centers: NDArray[np.float64]
    vocabulary: Vocabulary | None = None
    vocabulary_version: int = 0


EMPTY_INDEX = RetrievalIndex([], np.zeros((0, 1), np.float32), np.zeros((0, 3)))


def empty_index(vocabulary: VocabularyState | None) -> RetrievalIndex:
    """An index of no reference, tagged with ``vocabulary`` when there is one."""
    if vocabulary is None:
        return EMPTY_INDEX
    return replace(
        EMPTY_INDEX, vocabulary=vocabulary.vocabulary, vocabulary_version=vocabulary.version
    )
