"""Reference images of a map: add, list, get, delete."""

from __future__ import annotations

import logging
import uuid
from dataclasses import dataclass, replace
from datetime import datetime

from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from app.usecases.errors import MissingBlobError, NameTakenError, NotFoundError
from app.usecases.maps import require_map
from app.usecases.served_features import map_localizer
from db.blobs import BlobStore
from db.models import ReferenceImage
from db.originals import StoredOriginals, read_original, remove_blobs, write_originals
from db.repositories.images import ImageRepository
from db.repositories.maps import MapRepository
from db.store import camera_of, gps_of, pose_of
from db.vocabulary import SqlVocabularyStore
from services.components import Localizers
from services.geo.gps import GpsFix, gps_from_exif
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d
from services.imaging.decode import check_pixel_limit, decode_image_reduced
from services.imaging.preview import Preview, make_preview
from services.localization.localizer import Localizer
from services.references.cache import ReferenceFeatureCache
from services.retrieval.training import BackgroundTrainer
from services.retrieval.vlad_index import VladIndexer
from services.runtime.worker_slots import WorkerSlots, holding

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class NewImage:
    """What is known of a reference image before it is described: its name in the map, its
    camera, its pose ``cam_from_world`` and optionally its GPS position."""

    name: str
    camera: Camera
    cam_from_world: Rigid3d
    gps: GpsFix | None = None


@dataclass(frozen=True)
class StoredImage:
    """A stored reference image."""

    id: str
    name: str
    camera: Camera
    cam_from_world: Rigid3d
    num_keypoints: int
    has_depth: bool
    created_at: datetime
    gps: GpsFix | None = None
    # the image's original bytes are in the blob store (False: added before they were kept)
    has_original: bool = False
    original_sha256: str | None = None
    # flagged stale by a capture session's frames (services/capture/freshness.py)
    stale_since: datetime | None = None
    stale_reason: str | None = None


@dataclass(frozen=True)
class Original:
    """A reference image's bytes as uploaded, their SHA-256 and media type."""

    data: bytes
    sha256: str
    media_type: str


def add_reference_image(
    sessions: sessionmaker[Session],
    localizers: Localizers,
    map_id: str,
    image: NewImage,
    image_bytes: bytes,
    depth_bytes: bytes | None = None,
    trainer: BackgroundTrainer | None = None,
    slots: WorkerSlots | None = None,
    preview_max_side: int = 0,
    blobs: BlobStore | None = None,
) -> StoredImage:
    """Describe and store a posed reference image: the row and all its features in one
    transaction, or nothing. Without a GPS position, the one in the image's EXIF is kept.
    With a ``trainer``, a retrieval vocabulary that the add makes due is trained in the
    background, so no request waits for it. ``slots`` is held while the image is described,
    with its memory (bounds concurrent engine work; None: unbounded). ``preview_max_side``
    > 0 stores a JPEG preview of the image with its longer side at most that many pixels.
    With ``blobs``, the image's bytes as sent (and the depth's) are kept there, written
    before the row commits and deleted again when it does not (``db/originals.py``).

    Raises:
        NotFoundError: unknown map.
        NameTakenError: the map has an image of that name (also when another add stored it
            while this one was describing the image).
        FeaturesUnavailableError: the map's feature configuration is not served here.
        ImageTooLargeError: the image's header claims more than the localizer's pixel limit.
        InvalidInputError: the image, depth or camera is unusable.
        BlobStoreError: the blob store cannot be reached or refuses the write (nothing
            stored).
    """
    taken = f"map already has an image named {image.name!r}"
    # before anything reads the image (EXIF included): a header claiming too many pixels is
    # 413, as on localize
    check_pixel_limit(image_bytes, localizers.served.max_pixels)
    if image.gps is None:
        image = replace(image, gps=gps_from_exif(image_bytes))
    with sessions() as session:
        map_row = require_map(session, map_id)
        if ImageRepository(session).name_exists(map_id, image.name):
            raise NameTakenError(taken)
        localizer = map_localizer(localizers, map_row)
    with holding(slots, localizer.upload_memory_mib(image_bytes, depth_bytes is not None)):
        data = localizer.describe_reference(image_bytes, image.camera, depth_bytes)
        preview = (
            make_preview(
                decode_image_reduced(image_bytes, localizer.max_pixels, preview_max_side).rgb,
                preview_max_side,
            )
            if preview_max_side > 0
            else None
        )
    image_id = str(uuid.uuid4())
    originals: StoredOriginals | None = None
    if blobs is not None:  # the blobs first: a row never names a blob not written
        originals = write_originals(blobs, map_id, image_id, image_bytes, depth_bytes)
    try:
        with sessions.begin() as session:
            require_map(session, map_id)  # deleted while we extracted
            row = ImageRepository(session).add(
                map_id,
                image.name,
                image.camera,
                image.cam_from_world,
                data,
                image.gps,
                image_id=image_id,
                originals=originals,
            )
            if preview is not None:
                ImageRepository(session).add_preview(row.id, preview)
            stored = _stored(row)
    except BaseException as exc:
        if blobs is not None and originals is not None:
            remove_blobs(blobs, originals.keys)
        if not isinstance(exc, IntegrityError):
            raise
        with sessions() as session:
            if MapRepository(session).get(map_id) is None:
                raise NotFoundError("map", map_id) from exc
        raise NameTakenError(taken) from exc
    logger.info(
        "map %s: added image %s (%r, %d keypoints)",
        map_id,
        stored.id,
        stored.name,
        stored.num_keypoints,
    )
    if trainer is not None:
        train_vocabulary_if_due(sessions, trainer, map_id, localizer)
    return stored


def train_vocabulary_if_due(
    sessions: sessionmaker[Session], trainer: BackgroundTrainer, map_id: str, localizer: Localizer
) -> None:
    """Schedules the training of the map's VLAD vocabulary for ``localizer``'s extractor
    when its references have made one due."""
    indexer = VladIndexer(SqlVocabularyStore(sessions, map_id, localizer.extractor.name))
    if indexer.due():
        trainer.schedule((map_id, localizer.extractor.name), indexer.train_if_due)


def list_images(
    sessions: sessionmaker[Session],
    map_id: str,
    offset: int,
    limit: int,
    stale: bool | None = None,
) -> tuple[list[StoredImage], int]:
    """A page of the map's images, oldest first, and their number (``stale``: only those
    flagged stale, or only those not).

    Raises:
        NotFoundError: unknown map.
    """
    with sessions() as session:
        require_map(session, map_id)
        rows, total = ImageRepository(session).page(map_id, offset, limit, stale)
        return [_stored(row) for row in rows], total


def get_image(sessions: sessionmaker[Session], map_id: str, image_id: str) -> StoredImage:
    """One image of the map.

    Raises:
        NotFoundError: unknown map or image.
    """
    with sessions() as session:
        row = ImageRepository(session).get(map_id, image_id)
        if row is None:
            require_map(session, map_id)
            raise NotFoundError("image", image_id)
        return _stored(row)


def get_preview(sessions: sessionmaker[Session], map_id: str, image_id: str) -> Preview:
    """The JPEG preview of one image of the map.

    Raises:
        NotFoundError: unknown map or image, or an image stored without a preview.
    """
    with sessions() as session:
        preview = ImageRepository(session).preview(map_id, image_id)
        if preview is None:
            get_image(sessions, map_id, image_id)
            raise NotFoundError("preview of image", image_id)
        return preview


def get_original(
    sessions: sessionmaker[Session], blobs: BlobStore, map_id: str, image_id: str
) -> Original:
    """The bytes of one image of the map as they were uploaded.

    Raises:
        NotFoundError: unknown map or image, or an image stored without its original (added
            before originals were kept).
        MissingBlobError: the row names an original the blob store does not hold.
        BlobStoreError: the blob store cannot be reached or refuses the read.
    """
    with sessions() as session:
        row = ImageRepository(session).get(map_id, image_id)
        if row is None:
            require_map(session, map_id)
            raise NotFoundError("image", image_id)
        key, sha256 = row.original_key, row.original_sha256
    if key is None or sha256 is None:
        raise NotFoundError("original of image", image_id)
    data = read_original(blobs, key)
    if data is None:
        raise MissingBlobError(image_id)
    return Original(data, sha256, _media_type(data))


def _media_type(data: bytes) -> str:
    if data.startswith(b"\xff\xd8"):
        return "image/jpeg"
    if data.startswith(b"\x89PNG"):
        return "image/png"
    return "application/octet-stream"


def delete_image(
    sessions: sessionmaker[Session],
    map_id: str,
    image_id: str,
    features_cache: ReferenceFeatureCache | None = None,
    blobs: BlobStore | None = None,
) -> None:
    """Delete an image and its features (and its entry in ``features_cache``); then, with
    ``blobs``, its originals (after the row's deletion committed: a crash in between leaves
    blobs without a row, which the sweep removes, never a row without its blobs).

    Raises:
        NotFoundError: unknown map or image.
    """
    with sessions.begin() as session:
        repository = ImageRepository(session)
        keys = repository.blob_keys(map_id, image_id)
        if not repository.delete(map_id, image_id):
            require_map(session, map_id)
            raise NotFoundError("image", image_id)
    if features_cache is not None:
        features_cache.discard(map_id, [image_id])
    if blobs is not None:
        remove_blobs(blobs, keys)


def _stored(row: ReferenceImage) -> StoredImage:
    return StoredImage(
        id=row.id,
        name=row.name,
        camera=camera_of(row),
        cam_from_world=pose_of(row),
        num_keypoints=row.num_keypoints,
        has_depth=row.has_depth,
        created_at=row.created_at,
        gps=gps_of(row),
        has_original=row.original_key is not None,
        original_sha256=row.original_sha256,
        stale_since=row.stale_since,
        stale_reason=row.stale_reason,
    )
