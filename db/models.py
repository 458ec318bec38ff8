"""Tables: maps, their posed reference images, each image's stored feature arrays, and the
capture sessions that extend maps."""

from __future__ import annotations

import re
import uuid
from datetime import UTC, datetime

from sqlalchemy import (
    JSON,
    BigInteger,
    DateTime,
    Float,
    ForeignKey,
    Integer,
    LargeBinary,
    String,
    Text,
    UniqueConstraint,
    false,
)
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import Mapped, mapped_column, relationship
from sqlalchemy.types import TypeDecorator

from db.base import Base


class UTCDateTime(TypeDecorator[datetime]):
    """Timezone-aware UTC datetimes on every backend (SQLite drops the offset on its own)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is not None and value.tzinfo is None:
            return value.replace(tzinfo=UTC)
        return value


def _new_id() -> str:
    return str(uuid.uuid4())


_STORED_ID = re.compile(r"[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}")


def is_stored_id(value: str) -> bool:
    """Whether ``value`` has the shape of the ids rows get (a UUID's canonical text). Anything
    else names no row, and is not sent to the database (PostgreSQL refuses NUL in text)."""
    return _STORED_ID.fullmatch(value) is not None


def _now() -> datetime:
    return datetime.now(UTC)


class Map(Base):
    __tablename__ = "maps"

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=_new_id)
    name: Mapped[str] = mapped_column(String(255), unique=True)
    description: Mapped[str | None] = mapped_column(Text)
    # services.estimators.registry.DEFAULT_ESTIMATOR, as maps made through the API (a test
    # checks they agree; the repository and ``open_map`` pass it explicitly)
    default_estimator: Mapped[str] = mapped_column(String(64), default="auto")
    # per-map feature options (None = the service's default)
    max_keypoints: Mapped[int | None] = mapped_column(Integer)
    max_side: Mapped[int | None] = mapped_column(Integer)
    # the options its references are being re-described with from their originals (the
    # pending_* columns, None = the default); the map serves max_keypoints / max_side until
    # every reference is described anew, then switches (app/usecases/reextraction.py)
    reextracting: Mapped[bool] = mapped_column(default=False, server_default=false())
    pending_max_keypoints: Mapped[int | None] = mapped_column(Integer)
    pending_max_side: Mapped[int | None] = mapped_column(Integer)
    # the feature configuration its references are described with (None: the server's,
    # SLLOC_FEATURES) and the one they are being re-described with (with reextracting)
    feature_preset: Mapped[str | None] = mapped_column(String(64))
    pending_preset: Mapped[str | None] = mapped_column(String(64))
    # the map takes the configuration its self-evaluation recommends (features "auto")
    features_auto: Mapped[bool] = mapped_column(default=False, server_default=false())
    # confidently localized queries that add a view become references (app/usecases/growth.py)
    grow_from_queries: Mapped[bool] = mapped_column(default=False, server_default=false())
    # references a capture session flags stale are deleted at once (app/usecases/captures.py)
    retire_stale: Mapped[bool] = mapped_column(default=False, server_default=false())
    # the similarity to the Earth (db/geo.py holds its stored form; None: not registered)
    geo_registration: Mapped[dict[str, object] | None] = mapped_column(JSON)
    # bumped by every image add and delete (cached retrieval indexes compare it)
    revision: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=_now)

    images: Mapped[list[ReferenceImage]] = relationship(
        back_populates="map", cascade="all, delete-orphan", passive_deletes=True
    )


class ReferenceImage(Base):
    """A posed reference image. The pose is ``cam_from_world``, quaternion ``[w, x, y, z]``."""

    __tablename__ = "reference_images"
    __table_args__ = (UniqueConstraint("map_id", "name", name="uq_reference_images_map_id_name"),)

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=_new_id)
    map_id: Mapped[str] = mapped_column(ForeignKey("maps.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(255))
    camera_model: Mapped[str] = mapped_column(String(32))
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    camera_params: Mapped[list[float]] = mapped_column(JSON)
    qw: Mapped[float] = mapped_column(Float)
    qx: Mapped[float] = mapped_column(Float)
    qy: Mapped[float] = mapped_column(Float)
    qz: Mapped[float] = mapped_column(Float)
    tx: Mapped[float] = mapped_column(Float)
    ty: Mapped[float] = mapped_column(Float)
    tz: Mapped[float] = mapped_column(Float)
    num_keypoints: Mapped[int] = mapped_column(Integer)
    has_depth: Mapped[bool] = mapped_column(default=False)
    feature_model: Mapped[str] = mapped_column(String(128))
    descriptor_model: Mapped[str] = mapped_column(String(128))
    # optional GPS position: WGS84 degrees, height in metres above the ellipsoid, accuracy 1-σ m
    gps_latitude: Mapped[float | None] = mapped_column(Float)
    gps_longitude: Mapped[float | None] = mapped_column(Float)
    gps_height: Mapped[float | None] = mapped_column(Float)
    gps_accuracy_m: Mapped[float | None] = mapped_column(Float)
    # version of the map vocabulary its stored "vlad" array was encoded with (None: none yet)
    vlad_version: Mapped[int | None] = mapped_column(Integer)
    # the extractor of its staged description (arrays of kinds "next:…") while its map is
    # re-described; None: none staged
    next_feature_model: Mapped[str | None] = mapped_column(String(128))
    # the original upload in the blob store (db/blobs.py): the image's bytes as sent and their
    # SHA-256, and the depth map's; None: added before originals were kept (or without depth)
    original_key: Mapped[str | None] = mapped_column(String(255))
    original_sha256: Mapped[str | None] = mapped_column(String(64))
    depth_key: Mapped[str | None] = mapped_column(String(255))
    # flagged stale: the frames of a capture session or the references a self-evaluation
    # held out that cover it no longer match it (services/capture/freshness.py); None: not
    # flagged
    stale_since: Mapped[datetime | None] = mapped_column(UTCDateTime)
    stale_reason: Mapped[str | None] = mapped_column(Text)
    # single-frame queries whose best retrieved reference it was, localized and failed
    # (app/usecases/query_outcomes.py)
    queries_localized: Mapped[int] = mapped_column(BigInteger, default=0, server_default="0")
    queries_failed: Mapped[int] = mapped_column(BigInteger, default=0, server_default="0")
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=_now)

    map: Mapped[Map] = relationship(back_populates="images")
    arrays: Mapped[list[FeatureArray]] = relationship(
        back_populates="image", cascade="all, delete-orphan", passive_deletes=True
    )


class FeatureArray(Base):
    """One numpy array of an image (keypoints, descriptors, scores, global descriptor, depth),
    stored as raw C-order bytes with its dtype and shape."""

    __tablename__ = "feature_arrays"

    image_id: Mapped[str] = mapped_column(
        ForeignKey("reference_images.id", ondelete="CASCADE"), primary_key=True
    )
    kind: Mapped[str] = mapped_column(String(32), primary_key=True)
    dtype: Mapped[str] = mapped_column(String(16))
    shape: Mapped[list[int]] = mapped_column(JSON)
    data: Mapped[bytes] = mapped_column(LargeBinary)

    image: Mapped[ReferenceImage] = relationship(back_populates="arrays")


class ReferencePreview(Base):
    """A JPEG preview of a reference image for display, its longer side bounded by the
    service's ``preview_max_side``; never read by the engine."""

    __tablename__ = "reference_previews"

    image_id: Mapped[str] = mapped_column(
        ForeignKey("reference_images.id", ondelete="CASCADE"), primary_key=True
    )
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    jpeg: Mapped[bytes] = mapped_column(LargeBinary)


class MapVocabulary(Base):
    """The current VLAD vocabulary of a map for one local-feature model: (K, D) float32
    k-means centres of the map's own stored descriptors. ``version`` grows with every
    training; reference images record the version their VLAD vector was encoded with."""

    __tablename__ = "map_vocabularies"

    map_id: Mapped[str] = mapped_column(ForeignKey("maps.id", ondelete="CASCADE"), primary_key=True)
    feature_model: Mapped[str] = mapped_column(String(128), primary_key=True)
    version: Mapped[int] = mapped_column(Integer)
    trained_images: Mapped[int] = mapped_column(Integer)
    shape: Mapped[list[int]] = mapped_column(JSON)
    centers: Mapped[bytes] = mapped_column(LargeBinary)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=_now)


class MapEvaluation(Base):
    """A self-evaluation of a map (``app/usecases/evaluations.py``): what was asked, how far it
    has come, and what it measured per configuration (``result``; None until done)."""

    __tablename__ = "map_evaluations"

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=_new_id)
    map_id: Mapped[str] = mapped_column(ForeignKey("maps.id", ondelete="CASCADE"), index=True)
    # queued, running, done, failed, cancelled
    state: Mapped[str] = mapped_column(String(16))
    request: Mapped[dict[str, object]] = mapped_column(JSON)
    # held-out queries localized so far, of every configuration's
    done: Mapped[int] = mapped_column(Integer, default=0)
    total: Mapped[int] = mapped_column(Integer, default=0)
    result: Mapped[dict[str, object] | None] = mapped_column(JSON)
    error: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=_now)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime)


class CaptureSession(Base):
    """A capture uploaded to extend a map (``app/usecases/captures.py``): its frames wait in
    ``capture_frames`` until the session is aligned to the map and each is added as a
    reference, or refused. ``result`` holds the alignment and the decision."""

    __tablename__ = "capture_sessions"
    __table_args__ = (UniqueConstraint("map_id", "name", name="uq_capture_sessions_map_id_name"),)

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=_new_id)
    map_id: Mapped[str] = mapped_column(ForeignKey("maps.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(255))
    # the session's poses are in metres (else its scale is estimated)
    metric: Mapped[bool] = mapped_column(default=True)
    # every frame is added (else only those that add a view, services/capture/spacing.py)
    keep_all: Mapped[bool] = mapped_column(default=False)
    # open, queued, aligning, adding, added, refused, failed
    state: Mapped[str] = mapped_column(String(16))
    frame_count: Mapped[int] = mapped_column(Integer, default=0)
    # frames checked and added so far, of ``total``
    done: Mapped[int] = mapped_column(Integer, default=0)
    total: Mapped[int] = mapped_column(Integer, default=0)
    result: Mapped[dict[str, object] | None] = mapped_column(JSON)
    error: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=_now)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime)


class CaptureFrame(Base):
    """A frame of a capture session not yet added to its map: its camera, its pose in the
    session (``cam_from_session``, COLMAP camera axes) and its originals in the blob store,
    under the keys the reference it becomes keeps (its id is the reference's)."""

    __tablename__ = "capture_frames"
    __table_args__ = (
        UniqueConstraint("session_id", "name", name="uq_capture_frames_session_name"),
    )

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=_new_id)
    session_id: Mapped[str] = mapped_column(
        ForeignKey("capture_sessions.id", ondelete="CASCADE"), index=True
    )
    # the capture order (upload order)
    position: Mapped[int] = mapped_column(Integer)
    name: Mapped[str] = mapped_column(String(255))
    camera_model: Mapped[str] = mapped_column(String(32))
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    camera_params: Mapped[list[float]] = mapped_column(JSON)
    qw: Mapped[float] = mapped_column(Float)
    qx: Mapped[float] = mapped_column(Float)
    qy: Mapped[float] = mapped_column(Float)
    qz: Mapped[float] = mapped_column(Float)
    tx: Mapped[float] = mapped_column(Float)
    ty: Mapped[float] = mapped_column(Float)
    tz: Mapped[float] = mapped_column(Float)
    original_key: Mapped[str] = mapped_column(String(255))
    original_sha256: Mapped[str] = mapped_column(String(64))
    depth_key: Mapped[str | None] = mapped_column(String(255))
    # its pose in the map once the session is aligned (``cam_from_map``: [qw, qx, qy, qz, tx,
    # ty, tz]); None before
    placed: Mapped[list[float] | None] = mapped_column(JSON)
    # the device's GPS fix when it was taken (else its EXIF's), kept on the reference it becomes
    gps_latitude: Mapped[float | None] = mapped_column(Float)
    gps_longitude: Mapped[float | None] = mapped_column(Float)
    gps_height: Mapped[float | None] = mapped_column(Float)
    gps_accuracy_m: Mapped[float | None] = mapped_column(Float)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=_now)
