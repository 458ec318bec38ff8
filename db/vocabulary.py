"""Where a map's VLAD vocabulary and its references' VLAD vectors are stored: the SQL side of
``services.retrieval.vlad_index`` (which decides when to train, trains and encodes).

The published vocabulary is one ``map_vocabularies`` row per (map, feature model); each
reference keeps one current vector (``feature_arrays`` kind ``vlad``) and the version it was
encoded with (``reference_images.vlad_version``). A version being trained keeps its vectors
under a staging kind until it is published in one transaction.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
from sqlalchemy import ColumnElement, delete, func, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from db.arrays import from_row, to_row
from db.locks import exclusive
from db.models import FeatureArray, Map, MapVocabulary, ReferenceImage
from services.retrieval.contracts import Encoder, VocabularyError, VocabularyState
from services.retrieval.vlad import Vocabulary
from services.types import Float32Array

logger = logging.getLogger(__name__)

VLAD_KIND = "vlad"  # feature_arrays.kind of the current VLAD vectors
STAGED_PREFIX = "vlad-staged-"  # kind prefix of vectors of a version not yet published


def read_vocabulary(session: Session, map_id: str, feature_model: str) -> VocabularyState | None:
    row = session.get(MapVocabulary, (map_id, feature_model))
    if row is None:
        return None
    centers = np.frombuffer(row.centers, dtype="<f4").reshape(row.shape).astype(np.float32)
    empty = np.zeros(0, np.float32), np.zeros((0, 0), np.float32)
    return VocabularyState(row.version, Vocabulary(centers, *empty), row.trained_images)


class SqlVocabularyStore:
    """``VocabularyStore`` of one map and feature model; each call is its own transaction."""

    def __init__(self, sessions: sessionmaker[Session], map_id: str, feature_model: str) -> None:
        self.sessions = sessions
        self.map_id = map_id
        self.feature_model = feature_model

    def _images(self) -> tuple[ColumnElement[bool], ...]:
        return (
            ReferenceImage.map_id == self.map_id,
            ReferenceImage.feature_model == self.feature_model,
        )

    def count(self) -> int:
        with self.sessions() as session:
            stmt = select(func.count()).select_from(ReferenceImage).where(*self._images())
            return int(session.scalar(stmt) or 0)

    def published(self) -> VocabularyState | None:
        with self.sessions() as session:
            return read_vocabulary(session, self.map_id, self.feature_model)

    def reference_ids(self) -> list[str]:
        with self.sessions() as session:
            return list(
                session.scalars(
                    select(ReferenceImage.id)
                    .where(*self._images())
                    .order_by(ReferenceImage.created_at, ReferenceImage.id)
                )
            )

    def descriptors(self, image_ids: list[str]) -> dict[str, Float32Array]:
        with self.sessions() as session:
            return _descriptors(session, image_ids)

    @contextmanager
    def training_lock(self, wait_s: float = 0.0) -> Iterator[bool]:
        """The map and model's training lock across every process on the database."""
        engine = self.sessions.kw["bind"]
        name = f"vocabulary:{self.map_id}:{self.feature_model}"
        with exclusive(engine, name, wait_s) as held:
            yield held

    def stage(self, vectors: dict[str, Float32Array], tag: str) -> None:
        try:
            with self.sessions.begin() as session:
                _write(session, vectors, STAGED_PREFIX + tag)
        except IntegrityError:  # a reference was deleted meanwhile: publishing fills gaps
            logger.info("map %s: VLAD staging raced with a delete", self.map_id)

    def publish(
        self,
        vocabulary: Vocabulary,
        tag: str,
        trained_images: int,
        previous: VocabularyState | None,
        encoder: Encoder,
        yield_to_newer: bool,
    ) -> VocabularyState:
        staged = STAGED_PREFIX + tag
        in_map = select(ReferenceImage.id).where(*self._images())
        try:
            with self.sessions.begin() as session:
                map_row = session.get(Map, self.map_id, with_for_update=True)
                if map_row is None:
                    raise VocabularyError(f"map {self.map_id} was deleted while training")
                current = read_vocabulary(session, self.map_id, self.feature_model)
                newer = (None if current is None else current.version) != (
                    None if previous is None else previous.version
                )
                if yield_to_newer and newer:  # another trainer published first
                    session.execute(delete(FeatureArray).where(FeatureArray.kind == staged))
                    if current is None:
                        raise VocabularyError(f"map {self.map_id}'s vocabulary was removed")
                    return current
                has_staged = select(FeatureArray.image_id).where(FeatureArray.kind == staged)
                missing = list(session.scalars(in_map.where(~ReferenceImage.id.in_(has_staged))))
                if missing:
                    found = _descriptors(session, missing)
                    empty = np.zeros((0, vocabulary.centers.shape[1]), np.float32)
                    _write(session, {i: encoder(found.get(i, empty)) for i in missing}, staged)
                    session.flush()
                in_map_arrays = FeatureArray.image_id.in_(in_map)
                session.execute(
                    delete(FeatureArray).where(in_map_arrays, FeatureArray.kind == VLAD_KIND)
                )
                session.execute(
                    update(FeatureArray)
                    .where(in_map_arrays, FeatureArray.kind == staged)
                    .values(kind=VLAD_KIND)
                )
                session.execute(  # vectors left by trainers that stopped or lost
                    delete(FeatureArray).where(
                        in_map_arrays, FeatureArray.kind.startswith(STAGED_PREFIX)
                    )
                )
                version = 1 if current is None else current.version + 1
                session.execute(
                    update(ReferenceImage).where(*self._images()).values(vlad_version=version)
                )
                row = session.get(MapVocabulary, (self.map_id, self.feature_model))
                if row is None:
                    row = MapVocabulary(map_id=self.map_id, feature_model=self.feature_model)
                    session.add(row)
                centers = vocabulary.centers.astype("<f4")
                row.version = version
                row.trained_images = trained_images
                row.shape = list(centers.shape)
                row.centers = centers.tobytes()
                map_row.revision += 1
        except IntegrityError as exc:  # the map was deleted while publishing
            raise VocabularyError(f"map {self.map_id} changed while publishing: {exc}") from exc
        return VocabularyState(version, vocabulary, trained_images)

    def stale_ids(self, version: int, limit: int) -> list[str]:
        stale = or_(ReferenceImage.vlad_version.is_(None), ReferenceImage.vlad_version != version)
        with self.sessions() as session:
            return list(
                session.scalars(
                    select(ReferenceImage.id).where(*self._images(), stale).limit(limit)
                )
            )

    def replace_vectors(self, vectors: dict[str, Float32Array], version: int) -> bool:
        ids = list(vectors)
        try:
            with self.sessions.begin() as session:
                # the images first (as every writer): a delete of one waits for this
                session.execute(
                    select(ReferenceImage.id)
                    .where(ReferenceImage.id.in_(ids))
                    .order_by(ReferenceImage.id)
                    .with_for_update(read=True, key_share=True)
                )
                session.execute(
                    delete(FeatureArray).where(
                        FeatureArray.image_id.in_(ids), FeatureArray.kind == VLAD_KIND
                    )
                )
                _write(session, vectors, VLAD_KIND)
                session.execute(
                    update(ReferenceImage)
                    .where(ReferenceImage.id.in_(ids))
                    .values(vlad_version=version)
                )
        except IntegrityError:
            return False
        return True


def _descriptors(session: Session, image_ids: list[str]) -> dict[str, Float32Array]:
    rows = session.scalars(
        select(FeatureArray).where(
            FeatureArray.image_id.in_(image_ids), FeatureArray.kind == "descriptors"
        )
    )
    return {row.image_id: from_row(row).astype(np.float32) for row in rows}


def _write(session: Session, vectors: dict[str, Float32Array], kind: str) -> None:
    """Add ``vectors`` as arrays of ``kind`` for the references still stored."""
    existing = set(
        session.scalars(select(ReferenceImage.id).where(ReferenceImage.id.in_(list(vectors))))
    )
    for image_id, vector in vectors.items():
        if image_id in existing:
            session.add(to_row(image_id, kind, vector))
