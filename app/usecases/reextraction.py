"""A map's feature configuration or options changed: its references are described anew from
their originals in the background while the map keeps answering with its current descriptions,
and the map switches to the new ones at once when every reference that has its original is
described.

The work runs on one background thread at the lowest CPU priority (``BackgroundTrainer``),
in batches that each commit, so that a restart loses at most the batch in progress: at
start-up the maps still re-describing are scheduled again and the staged descriptions are
kept.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from app.usecases.errors import ConflictError
from app.usecases.maps import FeatureChoice, MapRecord, require_map
from db.blobs import BlobStore, BlobStoreError
from db.originals import read_original
from db.repositories.maps import MapRepository
from db.repositories.reextraction import Progress, ReextractionRepository
from db.store import camera_of
from services.components import Localizers
from services.errors import InvalidInputError
from services.geometry.camera import Camera
from services.localization.localizer import Localizer
from services.references.cache import ReferenceFeatureCache
from services.retrieval.training import BackgroundTrainer
from services.runtime.worker_slots import WorkerSlots, holding

logger = logging.getLogger(__name__)

# references described per transaction: a restart repeats at most this many
BATCH = 8


def reextraction_progress(
    sessions: sessionmaker[Session], localizers: Localizers, record: MapRecord
) -> Progress | None:
    """How far the map's re-description has come (None: none in progress, or for a
    configuration this server does not serve)."""
    if not record.reextracting:
        return None
    try:
        target = _target_model(
            localizers,
            record.pending_preset,
            record.pending_max_keypoints,
            record.pending_max_side,
        )
    except InvalidInputError:
        return None
    with sessions() as session:
        return ReextractionRepository(session).progress(record.id, target)


def change_feature_options(
    sessions: sessionmaker[Session],
    localizers: Localizers,
    map_id: str,
    options: FeatureChoice,
    reextractor: Reextractor | None,
) -> None:
    """Gives the map this feature configuration and options: at once when its references
    are described for them already (none, or that configuration's extractor at these
    options); else they are described anew from their originals in the background
    (``reextractor``) and the map switches when they are. Asking for what the map serves
    cancels a re-description in progress; on a map whose references another extractor
    described (the server's ``SLLOC_FEATURES`` changed), it describes them anew.

    Raises:
        NotFoundError: unknown map.
        InvalidInputError: a configuration not served here, or its extractor cannot honour
            the options.
        ConflictError: some references have no original to be described again from.
    """
    preset, max_keypoints, max_side = options
    target = _target_model(localizers, preset, max_keypoints, max_side)
    with sessions.begin() as session:
        row = require_map(session, map_id)
        repository = ReextractionRepository(session)
        progress = repository.progress(map_id, target)
        without_original = repository.without_original(map_id, target)
        serving = (row.feature_preset or localizers.features, row.max_keypoints, row.max_side)
        if serving == (preset or localizers.features, max_keypoints, max_side) and not (
            progress.total or without_original
        ):
            if row.reextracting:
                repository.cancel(map_id)
                logger.info("map %s: re-description cancelled", map_id)
            return
        if without_original:
            raise ConflictError(
                f"{without_original} of the map's references were added before originals "
                "were kept and cannot be described again: add them again, or delete them, "
                "before changing the map's feature options"
            )
        if not progress.total:  # every reference is described for these options already
            row.feature_preset, row.max_keypoints, row.max_side = options
            repository.cancel(map_id)
            return
        repository.start(map_id, *options)
    logger.info(
        "map %s: re-describing its references with %s, max_keypoints %s, max_side %s (%s)",
        map_id,
        preset or localizers.features,
        max_keypoints,
        max_side,
        target,
    )
    if reextractor is not None:
        reextractor.schedule(map_id)


class Reextractor:
    """Describes the references of re-describing maps anew, one map at a time."""

    def __init__(
        self,
        sessions: sessionmaker[Session],
        localizers: Localizers,
        blobs: BlobStore,
        features_cache: ReferenceFeatureCache | None = None,
        on_switch: Callable[[str, Localizer], None] | None = None,
        slots: WorkerSlots | None = None,
        queue_evaluation: Callable[[Session, str], Callable[[], None] | None] | None = None,
    ) -> None:
        """``on_switch(map_id, localizer)``: called after a map switched, with the
        localizer of its new options (e.g. to train its retrieval vocabulary); ``slots``:
        held around each description with its memory (a description computes in a
        localize worker's place; None: unbounded); ``queue_evaluation(session, map_id)``:
        called in the switch's own transaction, it stores the evaluation the switched map
        is due, if any, and returns what starts it once the switch is committed (so that
        the map never reads ready between its switch and that evaluation)."""
        self.slots = slots
        self.queue_evaluation = queue_evaluation
        self.sessions = sessions
        self.localizers = localizers
        self.blobs = blobs
        self.features_cache = features_cache
        self.on_switch = on_switch
        self.worker = BackgroundTrainer("re-extraction")
        self.described = 0  # references described since start-up
        self._lock = threading.Lock()

    def resume(self) -> None:
        """Schedules every map still re-describing (after a restart), read in the background
        so that a start-up does not wait on the database; an unreachable database leaves
        them to the next start or ``PATCH``."""
        self.worker.schedule("resume", self._resume)

    def _resume(self) -> None:
        try:
            with self.sessions() as session:
                pending = ReextractionRepository(session).maps_pending()
        except SQLAlchemyError as exc:
            logger.warning("re-descriptions not resumed, the database is unreachable: %s", exc)
            return
        if pending:
            logger.info("re-describing the references of %d maps: %s", len(pending), pending)
        for map_id in pending:
            self.schedule(map_id)

    def schedule(self, map_id: str) -> None:
        self.worker.schedule(map_id, lambda: self.run(map_id))

    def run(self, map_id: str) -> None:
        """Describes the map's references batch by batch, then switches it; returns early
        when the map is deleted or its re-description cancelled."""
        failed: set[str] = set()
        while True:
            with self.sessions() as session:
                row = MapRepository(session).get(map_id)
                if row is None or not row.reextracting:
                    return
                options = FeatureChoice(
                    row.pending_preset, row.pending_max_keypoints, row.pending_max_side
                )
                try:
                    localizer = self.localizers.for_map(
                        options.max_keypoints, options.max_side, options.preset
                    )
                except InvalidInputError as exc:  # e.g. a configuration no longer served
                    logger.warning("map %s: references not described again: %s", map_id, exc)
                    return
                target = localizer.extractor.name
                batch = [
                    (image.id, image.original_key, camera_of(image))
                    for image in ReextractionRepository(session).to_describe(
                        map_id, target, BATCH + len(failed)
                    )
                    if image.id not in failed
                ][:BATCH]
            if not batch and self._switch(map_id, localizer, options, failed):
                return
            for image_id, key, camera in batch:
                if not self._describe(map_id, image_id, key, camera, localizer):
                    failed.add(image_id)

    def _describe(
        self, map_id: str, image_id: str, key: str | None, camera: Camera, localizer: Localizer
    ) -> bool:
        try:
            original = read_original(self.blobs, key) if key is not None else None
            if original is None:
                raise InvalidInputError(f"its original {key} is missing from the blob store")
            with holding(self.slots, localizer.upload_memory_mib(original, False)):
                data = localizer.describe_reference(original, camera)
        except (InvalidInputError, BlobStoreError) as exc:
            logger.warning("map %s: reference %s not described again: %s", map_id, image_id, exc)
            return False
        with self.sessions.begin() as session:
            ReextractionRepository(session).stage(map_id, image_id, data)
        with self._lock:
            self.described += 1
        return True

    def _switch(
        self,
        map_id: str,
        localizer: Localizer,
        options: FeatureChoice,
        failed: set[str],
    ) -> bool:
        """Switches the map to its staged descriptions; False when its options changed
        since they were read (the run goes on with the new ones)."""
        with self.sessions.begin() as session:
            row = MapRepository(session).get(map_id)
            if row is None or not row.reextracting:
                return True  # deleted or cancelled meanwhile
            pending = (row.pending_preset, row.pending_max_keypoints, row.pending_max_side)
            if pending != options:
                return False
            switched = ReextractionRepository(session).switch(
                map_id, localizer.extractor.name, localizer.global_descriptor.name
            )
            start = self.queue_evaluation(session, map_id) if self.queue_evaluation else None
        if start is not None:
            start()
        if self.features_cache is not None:
            self.features_cache.discard(map_id)
        logger.info(
            "map %s: switched to %s (%d references described again, %d could not be)",
            map_id,
            localizer.extractor.name,
            switched,
            len(failed),
        )
        if self.on_switch is not None:
            self.on_switch(map_id, localizer)
        return True

    def shutdown(self) -> None:
        self.worker.shutdown()


def _target_model(
    localizers: Localizers, preset: str | None, max_keypoints: int | None, max_side: int | None
) -> str:
    return localizers.for_map(max_keypoints, max_side, preset).extractor.name
