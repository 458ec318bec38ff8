"""Maps that grow from their queries (the map setting ``grow_from_queries``, off by default).

A query the map localized with confidence ≥ ``GROW_CONFIDENCE``, sent with its intrinsics,
shows the place as it is now at a known pose. When it adds a view the map lacks — no reference
within the map's spacing looks within 15° of its direction (``services.capture.spacing``) —
it is added as a reference named ``query/<UTC time>-<id>``, its bytes kept as its original.
The spacing rule is the cap per place: a map grows where it is used until each place and
direction has its reference, then stops.

The additions run on one background thread at the lowest CPU priority, one pending per map (a
query offered while one waits is dropped), so a localize request never waits for them.
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Callable
from datetime import UTC, datetime

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from app.usecases.errors import ConflictError, NotFoundError
from app.usecases.images import NewImage, add_reference_image
from app.usecases.served_features import map_localizer
from db.blobs import BlobStore
from db.models import Map
from db.repositories.images import ImageRepository
from services.capture.spacing import map_spacing, new_views
from services.components import Localizers
from services.errors import InvalidInputError
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d
from services.localization.answer import LocalizationResult
from services.localization.localizer import Localizer
from services.retrieval.training import BackgroundTrainer
from services.runtime.worker_slots import WorkerSlots

logger = logging.getLogger(__name__)

GROW_CONFIDENCE = 0.95
NAME_PREFIX = "query/"


class QueryGrowth:
    """Adds the queries offered to it to their maps where they add a view."""

    def __init__(
        self,
        sessions: sessionmaker[Session],
        localizers: Localizers,
        blobs: BlobStore,
        slots: WorkerSlots | None = None,
        on_added: Callable[[str, Localizer], None] | None = None,
    ) -> None:
        """``slots``: held while a query is described, with its memory (None: unbounded);
        ``on_added``: called with the map's id and its localizer after an addition."""
        self.sessions = sessions
        self.localizers = localizers
        self.blobs = blobs
        self.slots = slots
        self.on_added = on_added
        self.worker = BackgroundTrainer("query growth")
        self.added = 0  # queries added since start-up

    def offer(
        self, map_id: str, image_bytes: bytes, camera: Camera | None, result: LocalizationResult
    ) -> bool:
        """Schedules the query's addition when it may grow the map: localized with
        confidence ≥ ``GROW_CONFIDENCE`` and sent with its camera. True when scheduled."""
        pose = result.cam_from_world
        if camera is None or pose is None or not result.localized:
            return False
        if result.confidence < GROW_CONFIDENCE:
            return False
        return self.worker.schedule(map_id, lambda: self._grow(map_id, image_bytes, camera, pose))

    def _grow(self, map_id: str, image_bytes: bytes, camera: Camera, pose: Rigid3d) -> None:
        with self.sessions() as session:
            row = session.get(Map, map_id)
            if row is None or not row.grow_from_queries:
                return
            localizer = map_localizer(self.localizers, row)
            poses = list(ImageRepository(session).poses(map_id).values())
        spacing = map_spacing(np.array([p.center for p in poses]))
        if spacing is None or not new_views([pose], poses, spacing):
            return
        name = f"{NAME_PREFIX}{datetime.now(UTC):%Y%m%dT%H%M%S}-{uuid.uuid4().hex[:8]}"
        try:
            stored = add_reference_image(
                self.sessions,
                self.localizers,
                map_id,
                NewImage(name, camera, pose),
                image_bytes,
                slots=self.slots,
                blobs=self.blobs,
            )
        except (NotFoundError, ConflictError, InvalidInputError) as exc:
            # the map deleted or changed meanwhile, or the query does not make a reference
            # (e.g. its camera does not fit the image as stored)
            logger.info("map %s: a query was not added: %s", map_id, exc)
            return
        self.added += 1
        logger.info("map %s grew from a query: reference %s (%s)", map_id, stored.id, name)
        if self.on_added is not None:
            self.on_added(map_id, localizer)

    def shutdown(self) -> None:
        self.worker.shutdown()
