"""Maps: create, list, get, delete."""

from __future__ import annotations

from dataclasses import dataclass, replace
from datetime import datetime
from typing import NamedTuple

from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from app.usecases.errors import NameTakenError, NotFoundError
from db.blobs import BlobStore
from db.models import Map
from db.originals import remove_blobs
from db.repositories.captures import CaptureRepository
from db.repositories.evaluations import EvaluationRepository
from db.repositories.images import ImageRepository
from db.repositories.maps import MapRepository
from services.components import Localizers
from services.errors import InvalidInputError
from services.estimators.registry import DEFAULT_ESTIMATOR
from services.features.configs import AUTO
from services.references.cache import ReferenceFeatureCache


class FeatureChoice(NamedTuple):
    """A map's feature configuration (None: the server's, ``SLLOC_FEATURES``; ``auto`` when
    creating: the one its self-evaluation recommends) and options (None: the
    configuration's)."""

    preset: str | None
    max_keypoints: int | None
    max_side: int | None


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
    # its feature configuration (None: the server's) and the one pending
    feature_preset: str | None = None
    pending_preset: str | None = None
    # it takes the configuration its self-evaluation recommends; one is queued or running
    features_auto: bool = False
    evaluating: bool = False
    # confidently localized queries that add a view become references
    grow_from_queries: bool = False
    # references a capture session flags stale are deleted at once
    retire_stale: bool = False


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
    localizers: Localizers,
    name: str,
    description: str | None,
    default_estimator: str,
    options: FeatureChoice,
    limits: FeatureLimits | None = None,
    grow_from_queries: bool = False,
    retire_stale: bool = False,
) -> MapRecord:
    """Create an empty map; ``options.preset`` ``auto`` (``AUTO``): served with the
    server's configuration until its self-evaluation recommends one.

    Raises:
        InvalidInputError: the feature options exceed ``limits``, a configuration this
            server does not serve, or its extractor cannot honour the options.
        NameTakenError: the name is taken.
    """
    preset, max_keypoints, max_side = options
    auto = preset == AUTO
    if limits is not None:
        limits.check(max_keypoints, max_side)
    localizers.for_map(max_keypoints, max_side, None if auto else preset)
    taken = f"a map named {name!r} exists"
    try:
        with sessions.begin() as session:
            repo = MapRepository(session)
            if repo.get_by_name(name) is not None:
                raise NameTakenError(taken)
            row = repo.create(
                name,
                description,
                default_estimator,
                max_keypoints,
                max_side,
                None if auto else preset,
                auto,
                grow_from_queries,
                retire_stale,
            )
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
    ``features_cache``) and its capture sessions; then, with ``blobs``, the originals of its
    images and of its sessions' waiting frames (after the deletion committed, as
    ``delete_image`` does).

    Raises:
        NotFoundError: no such map.
    """
    with sessions.begin() as session:
        keys = ImageRepository(session).blob_keys(map_id)
        keys += CaptureRepository(session).blob_keys(map_id)
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
    features_auto: bool | None = None,
    grow_from_queries: bool | None = None,
    retire_stale: bool | None = None,
) -> None:
    """Sets the map's ``description`` and ``default_estimator`` where named in ``fields``,
    whether it follows its self-evaluation, grows from its queries and retires its stale
    references (None: as it was).

    Raises:
        NotFoundError: no such map.
    """
    with sessions.begin() as session:
        row = require_map(session, map_id)
        if features_auto is not None:
            row.features_auto = features_auto
        if grow_from_queries is not None:
            row.grow_from_queries = grow_from_queries
        if retire_stale is not None:
            row.retire_stale = retire_stale
        if "description" in fields:
            row.description = description
        if "default_estimator" in fields and default_estimator is not None:
            row.default_estimator = default_estimator


def _records(repo: MapRepository, rows: list[Map]) -> list[MapRecord]:
    ids = [row.id for row in rows]
    counts = repo.image_counts(ids)
    evaluating = EvaluationRepository(repo.session).evaluating(ids)
    without = repo.without_original_counts(ids)
    described = repo.described_by(ids)
    return [
        replace(
            _record(row, counts.get(row.id, 0)),
            without_original=without.get(row.id, 0),
            described_by=tuple(described.get(row.id, ())),
            evaluating=row.id in evaluating,
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
        feature_preset=row.feature_preset,
        pending_preset=row.pending_preset,
        features_auto=row.features_auto,
        grow_from_queries=row.grow_from_queries,
        retire_stale=row.retire_stale,
    )
