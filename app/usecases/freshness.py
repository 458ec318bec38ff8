"""Stale references flagged from the votes of views that cover them (the frames of a capture
session, the references held out by a self-evaluation; ``services.capture.freshness``): the
references whose votes are all stale are flagged, or retired at once where the map says so,
and those with a fresh vote are unflagged."""

from __future__ import annotations

import logging
from datetime import UTC, datetime
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from app.usecases.maps import require_map
from db.blobs import BlobStore
from db.models import ReferenceImage
from db.originals import remove_blobs
from db.repositories.images import ImageRepository
from services.capture.freshness import Vote, stale_references
from services.references.cache import ReferenceFeatureCache

logger = logging.getLogger(__name__)


def flag_stale(
    sessions: sessionmaker[Session],
    blobs: BlobStore,
    features_cache: ReferenceFeatureCache | None,
    map_id: str,
    votes: list[Vote],
    source: str,
) -> list[dict[str, Any]]:
    """Stores the verdict of ``votes`` on the map's references; ``source`` names who voted in
    the reason stored (e.g. "capture session 'hall'"). Answers the stale ones as
    ``{image_id, name, reason, retired}``.

    Raises:
        NotFoundError: the map was deleted.
    """
    verdicts = stale_references(votes)
    now = datetime.now(UTC)
    stale: list[dict[str, Any]] = []
    retired: list[str] = []
    keys: list[str] = []
    with sessions.begin() as session:
        map_row = require_map(session, map_id)
        images = ImageRepository(session)
        for image_id, theirs in verdicts.items():
            row = session.get(ReferenceImage, image_id)
            if row is None:
                continue
            if not theirs:
                row.stale_since, row.stale_reason = None, None
                continue
            reason = (
                f"{source}: {len(theirs)} view(s) that cover it matched it with at most "
                f"{max(v.inliers for v in theirs)} inliers where the references they "
                f"retrieved had {min(v.expected for v in theirs)} or more"
            )
            if row.stale_since is None:
                row.stale_since = now
            row.stale_reason = reason
            entry = {"image_id": image_id, "name": row.name, "reason": reason}
            if map_row.retire_stale:  # the map retires them at once
                keys += images.blob_keys(map_id, image_id)
                images.delete(map_id, image_id)
                retired.append(image_id)
            stale.append(entry | {"retired": map_row.retire_stale})
    if retired:
        if features_cache is not None:
            features_cache.discard(map_id, retired)
        remove_blobs(blobs, keys)
    if stale:
        logger.info(
            "map %s: %d references flagged stale by %s, %d of them retired",
            map_id,
            len(stale),
            source,
            len(retired),
        )
    return stale
