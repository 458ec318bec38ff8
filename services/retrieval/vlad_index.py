"""A map's VLAD index kept current: when to train, training a vocabulary version from the map's
stored descriptors, encoding every reference with it, and publishing it, over a small storage
protocol (the database implements it).

Nothing here reads images. Training samples the stored descriptors of up to
``TRAINING_IMAGES`` references, reading ``VOCABULARY_READ`` of them at a time and drawing
``VOCABULARY_SAMPLE`` of their descriptors as if all were read at once; a new version is
staged beside the published one and published at once when every reference has its vector,
so retrieval keeps the previous index (or the global descriptors) until then. References
added after a publication are encoded with the published vocabulary the next time the index
is read; deleting references never needs training.
"""

from __future__ import annotations

import logging
import time
import uuid
from dataclasses import dataclass

import numpy as np

from services.retrieval.contracts import VocabularyError, VocabularyState, VocabularyStore
from services.retrieval.policy import TRAINING_IMAGES, num_centers, training_due
from services.retrieval.training import BackgroundTrainer
from services.retrieval.vlad import encode, sample_rows, train_vocabulary
from services.runtime.memory import VOCABULARY_READ, VOCABULARY_SAMPLE
from services.types import Float32Array

logger = logging.getLogger(__name__)

VOCABULARY_SEED = 0


@dataclass(frozen=True)
class ReindexReport:
    version: int
    num_centers: int
    trained_images: int
    encoded_images: int
    seconds: float


def searchable_vocabulary(
    indexer: VladIndexer, trainer: BackgroundTrainer | None
) -> VocabularyState | None:
    """The vocabulary a search uses now: the published one (None: global descriptors). A
    training found due goes to ``trainer`` and the search goes on with what is published;
    without a trainer (offline tools) it is trained first."""
    if trainer is None:
        try:
            indexer.train_if_due()
        except VocabularyError as exc:
            logger.warning("map %s: no retrieval vocabulary: %s", indexer.store.map_id, exc)
    elif indexer.due():
        trainer.schedule((indexer.store.map_id, indexer.store.feature_model), indexer.train_if_due)
    return indexer.current()


class VladIndexer:
    """Keeps one map's VLAD vectors up to date in ``store``."""

    def __init__(self, store: VocabularyStore) -> None:
        self.store = store

    def due(self) -> bool:
        """Whether the training policy asks for a new vocabulary now."""
        state = self.store.published()
        return training_due(self.store.count(), None if state is None else state.trained_images)

    def current(self) -> VocabularyState | None:
        """The published vocabulary (None while the map has none), with references added since
        it was published encoded first, so the index covers them."""
        state = self.store.published()
        if state is not None:
            self.encode_stale(state)
        return state

    def train_if_due(self) -> ReindexReport | None:
        """Train when the policy asks for it, holding the store's training lock so one
        process trains; None when not due or another process is training (its version is
        published when done). A version published meanwhile by an explicit ``train`` is kept
        instead of this one."""
        with self.store.training_lock() as held:
            if not held:
                logger.info("map %s: vocabulary training runs elsewhere", self.store.map_id)
                return None
            # checked under the lock: a trainer that held it before may just have published
            return self.train(yield_to_newer=True) if self.due() else None

    def train_now(self, wait_s: float) -> ReindexReport:
        """``train`` holding the store's training lock, after a training that holds it
        elsewhere is done, waiting for it at most ``wait_s`` seconds: one trainer at a time,
        and one due meanwhile finds nothing left to do once this version is published.

        Raises:
            VocabularyError: the other training went on for longer than ``wait_s``; or as
                ``train``.
        """
        with self.store.training_lock(wait_s) as held:
            if not held:
                raise VocabularyError(
                    f"map {self.store.map_id}'s retrieval vocabulary is being trained elsewhere "
                    f"(in the background or on another replica) for longer than {wait_s:g} s; "
                    "retry once that training is done"
                )
            return self.train()

    def train(self, yield_to_newer: bool = False) -> ReindexReport:
        """Train a new vocabulary version now, encode every reference with it, publish it (on
        top of any version published meanwhile, unless ``yield_to_newer``).

        Raises:
            VocabularyError: the map has too few references or descriptors, or was deleted.
        """
        start = time.perf_counter()
        previous = self.store.published()
        ids = self.store.reference_ids()
        rng = np.random.default_rng(0)
        picked = [ids[i] for i in np.sort(rng.permutation(len(ids))[:TRAINING_IMAGES])]
        sampling = np.random.default_rng(VOCABULARY_SEED)
        descriptors, total = self._training_sample(picked, sampling)
        centers = num_centers(descriptors[0].shape[1]) if descriptors else 1
        if total < centers:
            raise VocabularyError(
                f"map {self.store.map_id} has too few {self.store.feature_model} descriptors to "
                f"train a vocabulary ({len(ids)} reference images)"
            )
        # k-means goes on with the generator that drew the sample: the vocabulary is the one
        # train_vocabulary makes from all the descriptors at once
        vocabulary = train_vocabulary(descriptors, num_centers=centers, rng=sampling)

        def encoder(d: Float32Array) -> Float32Array:
            return encode(d, vocabulary)

        tag = uuid.uuid4().hex[:8]
        # encoded and staged a transaction per VOCABULARY_READ references, whose descriptors
        # are held at once (SIFT's 4096 keypoints: 2 MiB a reference)
        for first in range(0, len(ids), VOCABULARY_READ):
            batch = ids[first : first + VOCABULARY_READ]
            stored = self.store.descriptors(batch)
            self.store.stage({i: encoder(d) for i, d in stored.items()}, tag)
        state = self.store.publish(vocabulary, tag, len(ids), previous, encoder, yield_to_newer)
        seconds = time.perf_counter() - start
        logger.info(
            "map %s: VLAD vocabulary v%d (%s, K=%d) trained on %d of %d references in %.1f s",
            self.store.map_id,
            state.version,
            self.store.feature_model,
            centers,
            len(descriptors),
            len(ids),
            seconds,
        )
        return ReindexReport(
            state.version, int(vocabulary.centers.shape[0]), state.trained_images, len(ids), seconds
        )

    def _training_sample(
        self, picked: list[str], rng: np.random.Generator
    ) -> tuple[list[Float32Array], int]:
        """The descriptors of the picked references (in insertion order) k-means trains on,
        drawn with ``rng`` as ``train_vocabulary`` draws them from all at once, and their
        number before sampling. The descriptors are read ``VOCABULARY_READ`` references at a
        time, twice: to count them, then to keep the drawn rows."""
        counts: dict[str, int] = {}
        for first in range(0, len(picked), VOCABULARY_READ):
            stored = self.store.descriptors(picked[first : first + VOCABULARY_READ])
            counts.update({i: d.shape[0] for i, d in stored.items()})
        kept = [i for i in picked if i in counts]
        total = sum(counts[i] for i in kept)
        rows = sample_rows(total, VOCABULARY_SAMPLE, rng)
        if rows is None:
            rows = np.arange(total)
        starts = np.cumsum([0, *(counts[i] for i in kept)])
        bounds = np.searchsorted(rows, starts)  # each reference's share of the drawn rows
        sample: list[Float32Array] = []
        for first in range(0, len(kept), VOCABULARY_READ):
            batch = kept[first : first + VOCABULARY_READ]
            stored = self.store.descriptors(batch)
            for n, i in enumerate(batch, start=first):
                if i in stored:  # else deleted since it was counted
                    mine = rows[bounds[n] : bounds[n + 1]] - starts[n]
                    sample.append(np.ascontiguousarray(stored[i][mine]))
        return sample, total

    def encode_stale(self, state: VocabularyState) -> int:
        """Encode, in batches, the references whose vector is missing or of another version;
        returns how many were written."""
        written = 0
        while ids := self.store.stale_ids(state.version, VOCABULARY_READ):
            stored = self.store.descriptors(ids)
            dim = int(state.vocabulary.centers.shape[1])
            vectors = {
                i: encode(stored.get(i, np.zeros((0, dim), np.float32)), state.vocabulary)
                for i in ids
            }
            if not self.store.replace_vectors(vectors, state.version):
                logger.info(
                    "map %s: VLAD encoding raced with a delete; retrying later", self.store.map_id
                )
                return written
            written += len(ids)
        return written
