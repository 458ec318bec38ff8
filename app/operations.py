"""Use cases shared by the HTTP API and the CLI, so both take the same code path."""

from __future__ import annotations

import logging

from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from app.errors import conflict, not_found
from app.schemas.geometry import CameraSchema, PoseSchema
from app.schemas.images import ImageMetadata, ImageOut
from app.schemas.maps import ReindexOut
from db.models import ReferenceImage
from db.repositories.images import ImageRepository
from db.repositories.maps import MapRepository
from db.store import camera_of, pose_of
from db.vocabulary import SqlVocabularyStore
from services.pipeline import Localizer
from services.retrieval.training import BackgroundTrainer
from services.retrieval.vlad_index import VladIndexer, VocabularyError

logger = logging.getLogger(__name__)


def add_reference_image(
    sessions: sessionmaker[Session],
    localizer: Localizer,
    map_id: str,
    metadata: ImageMetadata,
    image_bytes: bytes,
    depth_bytes: bytes | None = None,
    trainer: BackgroundTrainer | None = None,
) -> ImageOut:
    """Describe and store a posed reference image: the row and all its features in one
    transaction, or nothing. With a ``trainer``, a retrieval vocabulary that the add makes due
    is trained in the background, so no request waits for it.

    Raises:
        ProblemError: 404 unknown map, 409 name taken.
        InvalidInputError: the image, depth or camera is unusable.
    """
    with sessions() as session:
        map_row = MapRepository(session).get(map_id)
        if map_row is None:
            raise not_found("map", map_id)
        if ImageRepository(session).name_exists(map_id, metadata.name):
            raise conflict(f"map already has an image named {metadata.name!r}")
        localizer = localizer.for_map(map_row.max_keypoints, map_row.max_side)
    camera = metadata.camera.to_camera()
    data = localizer.describe_reference(image_bytes, camera, depth_bytes)
    try:
        with sessions.begin() as session:
            if MapRepository(session).get(map_id) is None:  # deleted while we extracted
                raise not_found("map", map_id)
            row = ImageRepository(session).add(
                map_id, metadata.name, camera, metadata.cam_from_world.to_rigid(), data
            )
            out = image_out(row)
    except IntegrityError as exc:
        with sessions() as session:
            if MapRepository(session).get(map_id) is None:
                raise not_found("map", map_id) from exc
        raise conflict(f"map already has an image named {metadata.name!r}") from exc
    logger.info(
        "map %s: added image %s (%s, %d keypoints)", map_id, out.id, out.name, out.num_keypoints
    )
    if trainer is not None:
        indexer = VladIndexer(SqlVocabularyStore(sessions, map_id, localizer.extractor.name))
        if indexer.due():
            trainer.schedule((map_id, localizer.extractor.name), indexer.train_if_due)
    return out


def image_out(row: ReferenceImage) -> ImageOut:
    return ImageOut(
        id=row.id,
        name=row.name,
        camera=CameraSchema.from_camera(camera_of(row)),
        cam_from_world=PoseSchema.from_rigid(pose_of(row)),
        num_keypoints=row.num_keypoints,
        has_depth=row.has_depth,
        created_at=row.created_at,
    )


def reindex_map(
    sessions: sessionmaker[Session], localizer: Localizer, map_id: str, vlad: bool
) -> ReindexOut:
    """Train a new VLAD vocabulary version from the map's stored descriptors and re-encode
    every reference with it (no image is re-read).

    Raises:
        ProblemError: 404 unknown map; 409 when retrieval uses an ONNX global model
            (``vlad`` False) or the map has too few descriptors.
    """
    with sessions() as session:
        map_row = MapRepository(session).get(map_id)
        if map_row is None:
            raise not_found("map", map_id)
        localizer = localizer.for_map(map_row.max_keypoints, map_row.max_side)
    if not vlad:
        raise conflict(
            "retrieval uses the ONNX global-descriptor model (SLLOC_GLOBAL_MODEL); "
            "there is no vocabulary to train"
        )
    feature_model = localizer.extractor.name
    try:
        report = VladIndexer(SqlVocabularyStore(sessions, map_id, feature_model)).train()
    except VocabularyError as exc:
        raise conflict(str(exc)) from exc
    logger.info(
        "map %s: reindexed %d references with vocabulary v%d in %.1f s",
        map_id,
        report.encoded_images,
        report.version,
        report.seconds,
    )
    return ReindexOut(
        map_id=map_id,
        feature_model=feature_model,
        vocabulary_version=report.version,
        num_centers=report.num_centers,
        trained_images=report.trained_images,
        encoded_images=report.encoded_images,
        seconds=round(report.seconds, 3),
    )
