"""The engine's ``ReferenceStore`` backed by the database (one map, one feature model)."""

from __future__ import annotations

import logging
import math
from collections import defaultdict
from collections.abc import Callable

import numpy as np
from sqlalchemy import ColumnElement, select
from sqlalchemy.orm import Session, sessionmaker

from db.arrays import from_row
from db.blobs import BlobStore, BlobStoreError
from db.models import CaptureFrame, FeatureArray, Map, ReferenceImage
from db.originals import read_original
from db.vocabulary import VLAD_KIND
from services.errors import InvalidInputError
from services.features.base import LocalFeatures
from services.geo.gps import GpsFix
from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d, pose_problem
from services.references.cache import CachedFeatures, ReferenceFeatureCache
from services.references.store import ReferenceView
from services.retrieval.cache import RetrievalIndexCache
from services.retrieval.contracts import RetrievalIndex, VocabularyState, empty_index

logger = logging.getLogger(__name__)


def camera_of(row: ReferenceImage | CaptureFrame) -> Camera:
    return Camera(row.camera_model, row.width, row.height, tuple(row.camera_params))


def pose_of(row: ReferenceImage | CaptureFrame) -> Rigid3d:
    """A reference's ``cam_from_world``, a capture frame's ``cam_from_session``."""
    return Rigid3d.from_quaternion(
        np.array([row.qw, row.qx, row.qy, row.qz]), np.array([row.tx, row.ty, row.tz])
    )


def unusable(row: ReferenceImage) -> str | None:
    """Why a stored reference cannot take part in a localization, or None: a pose or
    intrinsics out of the range that adds accept now (a row stored before they were checked,
    or written by hand), which would only turn into overflows in the estimators."""
    problem = pose_problem(
        np.array([row.qw, row.qx, row.qy, row.qz], dtype=np.float64),
        np.array([row.tx, row.ty, row.tz], dtype=np.float64),
    )
    if problem is not None:
        return problem
    if not all(math.isfinite(float(v)) for v in row.camera_params):
        return "camera parameters must be finite numbers"
    if row.width <= 0 or row.height <= 0:
        return "camera size must be positive"
    return None


def gps_of(row: ReferenceImage | CaptureFrame) -> GpsFix | None:
    """A reference's or a capture frame's GPS position, None when it has none."""
    if row.gps_latitude is None or row.gps_longitude is None:
        return None
    try:
        return GpsFix(row.gps_latitude, row.gps_longitude, row.gps_height, row.gps_accuracy_m)
    except InvalidInputError:  # stored before its values were range-checked
        logger.warning("reference %s: stored GPS position ignored: out of range", row.id)
        return None


class SqlReferenceStore:
    """Reads the references of ``map_id`` whose features were made by ``feature_model`` and
    ``descriptor_model``; each call runs in its own short read transaction. With a ``cache``,
    the retrieval index is kept in memory between requests and caught up incrementally; with
    a ``features_cache``, the decoded features of the references read."""

    def __init__(
        self,
        sessions: sessionmaker[Session],
        map_id: str,
        feature_model: str,
        descriptor_model: str,
        cache: RetrievalIndexCache | None = None,
        vocabulary: Callable[[], VocabularyState | None] | None = None,
        features_cache: ReferenceFeatureCache | None = None,
        blobs: BlobStore | None = None,
    ) -> None:
        """``vocabulary``: the map's VLAD vocabulary to search with (None from it, or no
        callable: the localizer's global descriptors). ``features_cache``: keeps decoded
        reference features between requests. ``blobs``: where the references' originals are
        (None: the views name none)."""
        self.sessions = sessions
        self.cache = cache
        self.features_cache = features_cache
        self.map_id = map_id
        self.feature_model = feature_model
        self.descriptor_model = descriptor_model
        self._vocabulary = vocabulary
        self.blobs = blobs

    def retrieval_index(self) -> RetrievalIndex:
        if self.cache is None:
            return self.load_index(self.vocabulary())
        return self.cache.index(self)

    def vocabulary(self) -> VocabularyState | None:
        return None if self._vocabulary is None else self._vocabulary()

    def load_index(
        self, vocabulary: VocabularyState | None, only_ids: list[str] | None = None
    ) -> RetrievalIndex:
        """Descriptors and centres of the map's references (of ``only_ids`` when given):
        their VLAD vectors of ``vocabulary``'s version, or without one their global
        descriptors."""
        kind = "global_descriptor" if vocabulary is None else VLAD_KIND
        stmt = (
            select(ReferenceImage, FeatureArray)
            .join(FeatureArray, FeatureArray.image_id == ReferenceImage.id)
            .where(*self._references(), FeatureArray.kind == kind)
            .order_by(ReferenceImage.id)
        )
        if vocabulary is not None:
            stmt = stmt.where(ReferenceImage.vlad_version == vocabulary.version)
        if only_ids is not None:
            stmt = stmt.where(ReferenceImage.id.in_(only_ids))
        with self.sessions() as session:
            rows = session.execute(stmt).all()
        version = 0 if vocabulary is None else vocabulary.version
        if not rows:
            return empty_index(vocabulary)
        poses = [pose_of(image) for image, _ in rows]
        return RetrievalIndex(
            image_ids=[image.id for image, _ in rows],
            descriptors=np.stack([from_row(array) for _, array in rows]).astype(np.float32),
            centers=np.stack([pose.center for pose in poses]),
            vocabulary=None if vocabulary is None else vocabulary.vocabulary,
            vocabulary_version=version,
            axes=np.stack([pose.rotation[2] for pose in poses]),
        )

    def _references(self) -> tuple[ColumnElement[bool], ...]:
        return (
            ReferenceImage.map_id == self.map_id,
            ReferenceImage.feature_model == self.feature_model,
            ReferenceImage.descriptor_model == self.descriptor_model,
        )

    def revision(self) -> int | None:
        with self.sessions() as session:
            return session.scalar(select(Map.revision).where(Map.id == self.map_id))

    def reference_ids(self) -> list[str]:
        with self.sessions() as session:
            return list(session.scalars(select(ReferenceImage.id).where(*self._references())))

    def load_references(self, image_ids: list[str]) -> list[ReferenceView]:
        """The references with these ids, in that order, their existence checked in the
        database; features from the cache when it holds them, else decoded (and kept)."""
        if not image_ids:
            return []
        cache = self.features_cache
        generation = cache.generation() if cache is not None else 0
        with self.sessions() as session:
            images = {
                row.id: row
                for row in session.scalars(
                    select(ReferenceImage).where(
                        ReferenceImage.id.in_(image_ids), ReferenceImage.map_id == self.map_id
                    )
                )
            }
            cached = {i: self._cached(i) for i in images}
            missing = [i for i, entry in cached.items() if entry is None]
            arrays: dict[str, dict[str, np.ndarray]] = defaultdict(dict)
            if missing:
                for row in session.scalars(
                    select(FeatureArray).where(
                        FeatureArray.image_id.in_(missing),
                        FeatureArray.kind.in_(["keypoints", "descriptors", "scores", "depth"]),
                    )
                ):
                    arrays[row.image_id][row.kind] = from_row(row)
        views = []
        for image_id in image_ids:
            image = images.get(image_id)
            if image is None:  # deleted since retrieval
                continue
            problem = unusable(image)
            if problem is not None:
                logger.warning(
                    "map %s: reference %s left out of the localization: %s",
                    self.map_id,
                    image.id,
                    problem,
                )
                continue
            camera = camera_of(image)
            entry = cached[image_id] or self._decoded(image_id, camera, arrays, generation)
            if entry is None:  # deleted while its rows were read
                continue
            views.append(
                ReferenceView(
                    image_id=image.id,
                    name=image.name,
                    camera=camera,
                    cam_from_world=pose_of(image),
                    features=entry.features,
                    depth=entry.depth,
                    original_key=image.original_key if self.blobs is not None else None,
                )
            )
        return views

    def read_original(self, key: str) -> bytes | None:
        if self.blobs is None:
            return None
        try:
            return read_original(self.blobs, key)
        except BlobStoreError as exc:
            logger.warning("map %s: original %s not read: %s", self.map_id, key, exc)
            return None

    def _cached(self, image_id: str) -> CachedFeatures | None:
        if self.features_cache is None:
            return None
        return self.features_cache.get(self.map_id, image_id)

    def _decoded(
        self,
        image_id: str,
        camera: Camera,
        arrays: dict[str, dict[str, np.ndarray]],
        generation: int,
    ) -> CachedFeatures | None:
        stored = arrays.get(image_id, {})
        if "keypoints" not in stored:
            return None
        depth = stored.get("depth")
        entry = CachedFeatures(
            LocalFeatures(
                # the arrays read from the rows are already copies of their own: not copied again
                stored["keypoints"].astype(np.float32, copy=False),
                stored["descriptors"].astype(np.float32, copy=False),
                stored["scores"].astype(np.float32, copy=False),
                (camera.width, camera.height),
            ),
            depth.astype(np.float32, copy=False) if depth is not None else None,
        )
        if self.features_cache is not None:
            self.features_cache.put(self.map_id, image_id, entry, generation)
        return entry
