"""VLAD retrieval of a map, stored: its versioned vocabulary, trained from the map's own stored
local descriptors, and each reference's VLAD vector encoded with it.

Nothing here reads images: training samples the stored descriptors of up to
``TRAINING_IMAGES`` references, and encoding reads each reference's stored descriptors once.
When training is due is ``services.retrieval.policy``'s decision; training is always an explicit
step (``VladIndexer.train``), run in the background after an add, by ``POST
/v1/maps/{id}/reindex`` or by ``slloc reindex``. A new version is staged beside the current one
and published in one transaction once every reference is encoded with it, so retrieval keeps
the previous index (or the global descriptors) until then. Deleting references never needs it.
"""

from __future__ import annotations

import logging
import time
import uuid
from dataclasses import dataclass

import numpy as np
from sqlalchemy import ColumnElement, delete, func, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from db.arrays import from_row, to_row
from db.models import FeatureArray, Map, MapVocabulary, ReferenceImage
from services.retrieval.index import VocabularyState
from services.retrieval.policy import NUM_CENTERS, TRAINING_IMAGES, training_due
from services.retrieval.vlad import Vocabulary, encode, train_vocabulary

logger = logging.getLogger(__name__)

ENCODE_BATCH = 200  # references encoded per transaction
VLAD_KIND = "vlad"  # feature_arrays.kind of the stored VLAD vectors
STAGED_PREFIX = "vlad-staged-"  # kind prefix of vectors of a version not yet published


class VocabularyError(ValueError):
    """A vocabulary cannot be trained (too few references or descriptors)."""


@dataclass(frozen=True)
class ReindexReport:
    version: int
    num_centers: int
    trained_images: int
    encoded_images: int
    seconds: float


def read_vocabulary(session: Session, map_id: str, feature_model: str) -> VocabularyState | None:
    row = session.get(MapVocabulary, (map_id, feature_model))
    if row is None:
        return None
    centers = np.frombuffer(row.centers, dtype="<f4").reshape(row.shape).astype(np.float32)
    empty = np.zeros(0, np.float32), np.zeros((0, 0), np.float32)
    return VocabularyState(row.version, Vocabulary(centers, *empty), row.trained_images)


class VladIndexer:
    """Keeps the VLAD vectors of one map's references (of one feature model) up to date."""

    def __init__(self, sessions: sessionmaker[Session], map_id: str, feature_model: str) -> None:
        self.sessions = sessions
        self.map_id = map_id
        self.feature_model = feature_model

    def _images(self) -> tuple[ColumnElement[bool], ...]:
        return (
            ReferenceImage.map_id == self.map_id,
            ReferenceImage.feature_model == self.feature_model,
        )

    def current(self) -> VocabularyState | None:
        """The published vocabulary (None while the map has none); references added since it
        was published are encoded with it first, so the index covers them."""
        with self.sessions() as session:
            state = read_vocabulary(session, self.map_id, self.feature_model)
        if state is not None:
            self._encode_stale(state)
        return state

    def due(self) -> bool:
        """Whether the training policy asks for a new vocabulary now."""
        with self.sessions() as session:
            count = int(
                session.scalar(
                    select(func.count()).select_from(ReferenceImage).where(*self._images())
                )
                or 0
            )
            state = read_vocabulary(session, self.map_id, self.feature_model)
        return training_due(count, None if state is None else state.trained_images)

    def train_if_due(self) -> ReindexReport | None:
        return self.train() if self.due() else None

    def train(self) -> ReindexReport:
        """Train a new vocabulary version now, encode every reference with it, and publish it.

        Raises:
            VocabularyError: the map has too few references or descriptors, or was deleted.
        """
        start = time.perf_counter()
        with self.sessions() as session:
            previous = read_vocabulary(session, self.map_id, self.feature_model)
            ids = list(
                session.scalars(
                    select(ReferenceImage.id)
                    .where(*self._images())
                    .order_by(ReferenceImage.created_at, ReferenceImage.id)
                )
            )
            rng = np.random.default_rng(0)
            picked = [ids[i] for i in np.sort(rng.permutation(len(ids))[:TRAINING_IMAGES])]
            stored = self._descriptors(session, picked) if picked else {}
            descriptors = [stored[i] for i in picked if i in stored]  # in insertion order
        if sum(d.shape[0] for d in descriptors) < NUM_CENTERS:
            raise VocabularyError(
                f"map {self.map_id} has too few {self.feature_model} descriptors to train a "
                f"vocabulary ({len(ids)} reference images)"
            )
        vocabulary = train_vocabulary(descriptors, num_centers=NUM_CENTERS)
        staged = STAGED_PREFIX + uuid.uuid4().hex[:8]
        try:
            for first in range(0, len(ids), ENCODE_BATCH):
                self._stage(ids[first : first + ENCODE_BATCH], vocabulary, staged)
            state = self._publish(vocabulary, staged, len(ids), previous)
        except IntegrityError as exc:  # the map was deleted while training
            raise VocabularyError(f"map {self.map_id} changed while training: {exc}") from exc
        seconds = time.perf_counter() - start
        logger.info(
            "map %s: VLAD vocabulary v%d (%s, K=%d) trained on %d of %d references in %.1f s",
            self.map_id,
            state.version,
            self.feature_model,
            NUM_CENTERS,
            len(descriptors),
            len(ids),
            seconds,
        )
        return ReindexReport(
            state.version,
            int(state.vocabulary.centers.shape[0]),
            state.trained_images,
            len(ids),
            seconds,
        )

    def _descriptors(self, session: Session, image_ids: list[str]) -> dict[str, np.ndarray]:
        rows = session.scalars(
            select(FeatureArray).where(
                FeatureArray.image_id.in_(image_ids), FeatureArray.kind == "descriptors"
            )
        )
        return {row.image_id: from_row(row).astype(np.float32) for row in rows}

    def _write_vectors(
        self, session: Session, ids: list[str], vocabulary: Vocabulary, kind: str
    ) -> None:
        """Encode the references ``ids`` (those still stored) with ``vocabulary`` as ``kind``."""
        descriptors = self._descriptors(session, ids)
        existing = set(session.scalars(select(ReferenceImage.id).where(ReferenceImage.id.in_(ids))))
        dim = int(vocabulary.centers.shape[1])
        for image_id in ids:
            if image_id in existing:
                d = descriptors.get(image_id, np.zeros((0, dim), np.float32))
                session.add(to_row(image_id, kind, encode(d, vocabulary)))

    def _stage(self, ids: list[str], vocabulary: Vocabulary, staged: str) -> None:
        try:
            with self.sessions.begin() as session:
                self._write_vectors(session, ids, vocabulary, staged)
        except IntegrityError:  # a reference was deleted meanwhile: publishing fills gaps
            logger.info("map %s: VLAD staging raced with a delete", self.map_id)

    def _publish(
        self,
        vocabulary: Vocabulary,
        staged: str,
        trained_images: int,
        previous: VocabularyState | None,
    ) -> VocabularyState:
        """Make the staged version current in one transaction: references added since staging
        are encoded now, the staged vectors replace the current ones, the vocabulary row and
        the map revision are written. Another trainer that published first wins."""
        in_map = select(ReferenceImage.id).where(*self._images())
        with self.sessions.begin() as session:
            map_row = session.get(Map, self.map_id, with_for_update=True)
            if map_row is None:
                raise VocabularyError(f"map {self.map_id} was deleted while training")
            row = session.get(MapVocabulary, (self.map_id, self.feature_model))
            if (row is None) != (previous is None) or (
                row is not None and previous is not None and row.version != previous.version
            ):
                session.execute(delete(FeatureArray).where(FeatureArray.kind == staged))
                current = read_vocabulary(session, self.map_id, self.feature_model)
                if current is None:
                    raise VocabularyError(f"map {self.map_id}'s vocabulary was removed meanwhile")
                return current
            missing = list(
                session.scalars(
                    in_map.where(
                        ~ReferenceImage.id.in_(
                            select(FeatureArray.image_id).where(FeatureArray.kind == staged)
                        )
                    )
                )
            )
            if missing:
                self._write_vectors(session, missing, vocabulary, staged)
                session.flush()
            session.execute(
                delete(FeatureArray).where(
                    FeatureArray.image_id.in_(in_map), FeatureArray.kind == VLAD_KIND
                )
            )
            session.execute(
                update(FeatureArray)
                .where(FeatureArray.image_id.in_(in_map), FeatureArray.kind == staged)
                .values(kind=VLAD_KIND)
            )
            session.execute(
                delete(FeatureArray).where(
                    FeatureArray.image_id.in_(in_map), FeatureArray.kind.startswith(STAGED_PREFIX)
                )
            )
            version = 1 if row is None else row.version + 1
            session.execute(
                update(ReferenceImage).where(*self._images()).values(vlad_version=version)
            )
            centers = vocabulary.centers.astype("<f4")
            if row is None:
                row = MapVocabulary(map_id=self.map_id, feature_model=self.feature_model)
                session.add(row)
            row.version = version
            row.trained_images = trained_images
            row.shape = list(centers.shape)
            row.centers = centers.tobytes()
            map_row.revision += 1
        return VocabularyState(version, vocabulary, trained_images)

    def _encode_stale(self, state: VocabularyState) -> int:
        """Encode, in batches, the references whose VLAD vector is missing or of another
        version; returns how many were written."""
        stale = or_(
            ReferenceImage.vlad_version.is_(None), ReferenceImage.vlad_version != state.version
        )
        written = 0
        while True:
            try:
                with self.sessions.begin() as session:
                    ids = list(
                        session.scalars(
                            select(ReferenceImage.id)
                            .where(*self._images(), stale)
                            .limit(ENCODE_BATCH)
                        )
                    )
                    if not ids:
                        return written
                    session.execute(
                        delete(FeatureArray).where(
                            FeatureArray.image_id.in_(ids), FeatureArray.kind == VLAD_KIND
                        )
                    )
                    self._write_vectors(session, ids, state.vocabulary, VLAD_KIND)
                    session.execute(
                        update(ReferenceImage)
                        .where(ReferenceImage.id.in_(ids))
                        .values(vlad_version=state.version)
                    )
            except IntegrityError:  # a reference was deleted meanwhile; the next call retries
                logger.info(
                    "map %s: VLAD encoding raced with a delete; retrying later", self.map_id
                )
                return written
            written += len(ids)
