"""Maps: create, list, get, delete."""

from __future__ import annotations

from dataclasses import dataclass, replace
from datetime import datetime

from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from app.usecases.errors import NameTakenError, NotFoundError
from db.blobs import BlobStore
from db.models import Map
from db.originals import remove_blobs
from db.repositories.images import ImageRepository
from db.repositories.maps import MapRepository
from services.errors import InvalidInputError
from services.estimators.registry import DEFAULT_ESTIMATOR
from services.localization.localizer import Localizer
from services.references.cache import ReferenceFeatureCache


@dataclass(frozen=True)
class MapRecord:
    """A stored map; ``max_keypoints`` / ``max_side`` None keep the service's default."""

    id: str
    name: str
    description: str | None
    default_estimator: str
    max_keypoints: int | None
    max_side: int | None
    image_count: int
    created_at: datetime
    # its references without their originals in the blob store (added before they were kept)
    without_original: int = 0
    # (feature model, descriptor model, image count) its references were described by
    described_by: tuple[tuple[str, str, int], ...] = ()
    # its references are being described anew for these options (app/usecases/reextraction)
    reextracting: bool = False
    pending_max_keypoints: int | None = None
    pending_max_side: int | None = None


def require_map(session: Session, map_id: str) -> Map:
    """The map's row.

    Raises:
        NotFoundError: no such map.
    """
    row = MapRepository(session).get(map_id)
    if row is None:
        raise NotFoundError("map", map_id)
    return row


@dataclass(frozen=True)
class FeatureLimits:
    """The largest feature options a map may ask for: they bound the cost of every add and
    localize on it."""

    max_keypoints: int
    max_side: int

    def check(self, max_keypoints: int | None, max_side: int | None) -> None:
        """Raises:
        InvalidInputError: an option exceeds its limit.
        """
        for field, value, limit in (
            ("max_keypoints", max_keypoints, self.max_keypoints),
            ("max_side", max_side, self.max_side),
        ):
            if value is not None and value > limit:
                raise InvalidInputError(f"features.{field} may be at most {limit}")


def create_map(
    sessions: sessionmaker[Session],
    localizer: Localizer,
    name: str,
    description: str | None,
    default_estimator: str,
    max_keypoints: int | None,
    max_side: int | None,
    limits: FeatureLimits | None = None,
) -> MapRecord:
    """Create an empty map.

    Raises:
        InvalidInputError: the feature options exceed ``limits``, or the localizer's
            extractor cannot honour them.
        NameTakenError: the name is taken.
    """
    if limits is not None:
        limits.check(max_keypoints, max_side)
    localizer.for_map(max_keypoints, max_side)
    taken = f"a map named {name!r} exists"
    try:
        with sessions.begin() as session:
            repo = MapRepository(session)
            if repo.get_by_name(name) is not None:
                raise NameTakenError(taken)
            row = repo.create(name, description, default_estimator, max_keypoints, max_side)
            return _record(row, 0)
    except IntegrityError as exc:
        raise NameTakenError(taken) from exc


def open_map(sessions: sessionmaker[Session], name: str) -> MapRecord:
    """The map named ``name``, created empty with the service's defaults when there is none
    (those of a map created through the API: ``DEFAULT_ESTIMATOR``, the service's features).
    A creation that loses the race with another one (another import) opens the winner's map.

    Raises:
        NotFoundError: the map created meanwhile was deleted before it could be read.
    """
    found = _find_by_name(sessions, name)
    if found is not None:
        return found
    try:
        with sessions.begin() as session:
            row = MapRepository(session).create(name, None, DEFAULT_ESTIMATOR)
            return _record(row, 0)
    except IntegrityError:  # another creation of the name committed first
        found = _find_by_name(sessions, name)
        if found is None:
            raise NotFoundError("map", name) from None
        return found


def _find_by_name(sessions: sessionmaker[Session], name: str) -> MapRecord | None:
    with sessions() as session:
        repo = MapRepository(session)
        row = repo.get_by_name(name)
        return None if row is None else _records(repo, [row])[0]


def list_maps(
    sessions: sessionmaker[Session], offset: int, limit: int
) -> tuple[list[MapRecord], int]:
    """A page of maps, oldest first, and the number of maps."""
    with sessions() as session:
        repo = MapRepository(session)
        rows, total = repo.page(offset, limit)
        return _records(repo, rows), total


def get_map(sessions: sessionmaker[Session], map_id: str) -> MapRecord:
    """The map and its number of images.

    Raises:
        NotFoundError: no such map.
    """
    with sessions() as session:
        row = require_map(session, map_id)
        return _records(MapRepository(session), [row])[0]


def delete_map(
    sessions: sessionmaker[Session],
    map_id: str,
    features_cache: ReferenceFeatureCache | None = None,
    blobs: BlobStore | None = None,
) -> None:
    """Delete a map with its images and their features (and their entries in
    ``features_cache``); then, with ``blobs``, its images' originals (after the deletion
    committed, as ``delete_image`` does).

    Raises:
        NotFoundError: no such map.
    """
    with sessions.begin() as session:
        keys = ImageRepository(session).blob_keys(map_id)
        if not MapRepository(session).delete(map_id):
            raise NotFoundError("map", map_id)
    if features_cache is not None:
        features_cache.discard(map_id)
    if blobs is not None:
        remove_blobs(blobs, keys)


def update_map(
    sessions: sessionmaker[Session],
    map_id: str,
    description: str | None,
    default_estimator: str | None,
    fields: set[str],
) -> None:
    """Sets the map's ``description`` and ``default_estimator`` where named in ``fields``.

    Raises:
        NotFoundError: no such map.
    """
    with sessions.begin() as session:
        row = require_map(session, map_id)
        if "description" in fields:
            row.description = description
        if "default_estimator" in fields and default_estimator is not None:
            row.default_estimator = default_estimator


def _records(repo: MapRepository, rows: list[Map]) -> list[MapRecord]:
    ids = [row.id for row in rows]
    counts = repo.image_counts(ids)
    without = repo.without_original_counts(ids)
    described = repo.described_by(ids)
    return [
        replace(
            _record(row, counts.get(row.id, 0)),
            without_original=without.get(row.id, 0),
            described_by=tuple(described.get(row.id, ())),
        )
        for row in rows
    ]


def _record(row: Map, image_count: int) -> MapRecord:
    return MapRecord(
        id=row.id,
        name=row.name,
        description=row.description,
        default_estimator=row.default_estimator,
        max_keypoints=row.max_keypoints,
        max_side=row.max_side,
        image_count=image_count,
        created_at=row.created_at,
        reextracting=row.reextracting,
        pending_max_keypoints=row.pending_max_keypoints,
        pending_max_side=row.pending_max_side,
    )
