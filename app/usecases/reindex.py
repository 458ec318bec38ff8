"""Retrain a map's VLAD retrieval vocabulary."""

from __future__ import annotations

import logging
from dataclasses import dataclass

from sqlalchemy.orm import Session, sessionmaker

from app.usecases.errors import ConflictError
from app.usecases.maps import require_map
from app.usecases.served_features import map_localizer
from db.vocabulary import SqlVocabularyStore
from services.components import Localizers
from services.retrieval.contracts import VocabularyError
from services.retrieval.vlad_index import VladIndexer

logger = logging.getLogger(__name__)

# seconds a reindex waits for a training of the map running elsewhere (in the background, on
# another replica) before it answers 409, so that waiting holds a thread and a database
# connection for a bounded time
TRAINING_WAIT_S = 60.0


@dataclass(frozen=True)
class Reindexed:
    """A new vocabulary of ``map_id`` for the references of ``feature_model``.

    Attributes:
        vocabulary_version: grows by one with every training.
        num_centers: k-means centres K.
        trained_images: references in the map when it was trained.
        encoded_images: references re-encoded with it.
        seconds: wall time of training and encoding.
    """

    map_id: str
    feature_model: str
    vocabulary_version: int
    num_centers: int
    trained_images: int
    encoded_images: int
    seconds: float


def reindex_map(
    sessions: sessionmaker[Session], localizers: Localizers, map_id: str, vlad: bool
) -> Reindexed:
    """Train a new VLAD vocabulary version from the map's stored descriptors and re-encode
    every reference with it (no image is re-read), after a training of the map running
    meanwhile (a background one, or another replica's) is done.

    Raises:
        NotFoundError: unknown map, also one deleted while it was being trained.
        ConflictError: retrieval uses an ONNX global model (``vlad`` False), the map has too
            few descriptors, or a training running elsewhere went on for longer than
            ``TRAINING_WAIT_S``.
    """
    with sessions() as session:
        map_row = require_map(session, map_id)
        localizer = map_localizer(localizers, map_row)
    if not vlad:
        raise ConflictError(
            "retrieval uses the ONNX global-descriptor model (SLLOC_GLOBAL_MODEL); "
            "there is no vocabulary to train"
        )
    feature_model = localizer.extractor.name
    try:
        indexer = VladIndexer(SqlVocabularyStore(sessions, map_id, feature_model))
        report = indexer.train_now(TRAINING_WAIT_S)
    except VocabularyError as exc:
        with sessions() as session:
            require_map(session, map_id)  # gone meanwhile: not found, not a conflict
        raise ConflictError(str(exc)) from exc
    logger.info(
        "map %s: reindexed %d references with vocabulary v%d in %.1f s",
        map_id,
        report.encoded_images,
        report.version,
        report.seconds,
    )
    return Reindexed(
        map_id=map_id,
        feature_model=feature_model,
        vocabulary_version=report.version,
        num_centers=report.num_centers,
        trained_images=report.trained_images,
        encoded_images=report.encoded_images,
        seconds=report.seconds,
    )
