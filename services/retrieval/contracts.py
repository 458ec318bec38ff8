"""Retrieval contract types: a map's index as the engine searches it, the VLAD vocabulary it
may use, and the storage protocol of vocabularies and VLAD vectors."""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from services.retrieval.ann import AnnView
from services.retrieval.vlad import Vocabulary
from services.types import Float32Array, FloatArray


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
        ann: an approximate index over ``descriptors`` (large maps); None: exact search.
        axes: (N, 3) float64 optical axes in world axes (None: not known).
    """

    image_ids: list[str]
    descriptors: Float32Array
    centers: FloatArray
    vocabulary: Vocabulary | None = None
    vocabulary_version: int = 0
    ann: AnnView | None = None
    axes: FloatArray | None = None


EMPTY_INDEX = RetrievalIndex(
    [], np.zeros((0, 1), np.float32), np.zeros((0, 3)), axes=np.zeros((0, 3))
)


def empty_index(vocabulary: VocabularyState | None) -> RetrievalIndex:
    """An index of no reference, tagged with ``vocabulary`` when there is one."""
    if vocabulary is None:
        return EMPTY_INDEX
    return replace(
        EMPTY_INDEX, vocabulary=vocabulary.vocabulary, vocabulary_version=vocabulary.version
    )


Encoder = Callable[[Float32Array], Float32Array]


class VocabularyError(ValueError):
    """A vocabulary cannot be trained (too few references or descriptors, the map went, or
    another trainer of the map kept its training lock for longer than this one waits)."""


class VocabularyStore(Protocol):
    """Where one map's vocabulary and VLAD vectors (of one feature model) are kept."""

    map_id: str
    feature_model: str

    def count(self) -> int:
        """How many references the map has."""
        ...

    def published(self) -> VocabularyState | None: ...

    def reference_ids(self) -> list[str]:
        """Every reference id, in insertion order."""
        ...

    def descriptors(self, image_ids: list[str]) -> dict[str, Float32Array]:
        """(N, D) local descriptors of the references among ``image_ids`` still stored."""
        ...

    def training_lock(self, wait_s: float = 0.0) -> AbstractContextManager[bool]:
        """Held while a vocabulary is trained, by one trainer at a time across every process
        sharing the store; yields False when another trainer kept it for ``wait_s`` seconds
        (0: at once)."""
        ...

    def stage(self, vectors: dict[str, Float32Array], tag: str) -> None:
        """Keep ``vectors`` of an unpublished version under ``tag`` (references deleted
        meanwhile are skipped)."""
        ...

    def publish(
        self,
        vocabulary: Vocabulary,
        tag: str,
        trained_images: int,
        previous: VocabularyState | None,
        encoder: Encoder,
        yield_to_newer: bool,
    ) -> VocabularyState:
        """Atomically: encode with ``encoder`` the references that have no staged vector, make
        the staged vectors current, store ``vocabulary`` as the next version. When
        ``yield_to_newer`` and another trainer published since ``previous`` was read, drop the
        staged vectors and return its version instead.

        Raises:
            VocabularyError: the map was deleted.
        """
        ...

    def stale_ids(self, version: int, limit: int) -> list[str]:
        """Up to ``limit`` references without a vector of ``version``."""
        ...

    def replace_vectors(self, vectors: dict[str, Float32Array], version: int) -> bool:
        """Store current vectors of ``version``; False when a reference was deleted meanwhile
        (nothing written)."""
        ...
