"""The originals of reference images in the blob store, kept consistent with their rows.

The rule: **no row without its blobs, no blob without its row** (beyond a grace period).

* An add writes the blobs first, under keys made of the map's and the new image's ids
  (:func:`original_key`, :func:`depth_key`), then commits the row that names them; when the
  row does not commit, the add deletes the blobs it wrote.
* A delete commits the row's deletion first, then deletes the blobs.
* A capture session's frame is a row of its own (``capture_frames``) whose blobs are written
  under the keys of the reference it becomes; the reference row is inserted and the frame's
  deleted in one transaction, so the blobs always have exactly one row.
* A process killed between the two steps leaves only blobs without a row, never a row
  without its blob; :func:`reconcile` (run at start-up and by ``slloc blobs sweep``) removes
  those older than a grace period, which must exceed the longest time between an add's
  blob write and its commit, and reports rows whose blob is missing (none, unless someone
  removed blobs by hand).
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta

from sqlalchemy import or_, select
from sqlalchemy.orm import Session, sessionmaker

from db.blobs import BlobInfo, BlobNotFoundError, BlobStore, FileBlobStore
from db.models import CaptureFrame, ReferenceImage

logger = logging.getLogger(__name__)

ORIGINALS_PREFIX = "originals/"
IMAGE_NAME = "image"
DEPTH_NAME = "depth"
# rows and blobs compared per query
_CHUNK = 500


def original_key(map_id: str, image_id: str) -> str:
    """The key of a reference image's original bytes."""
    return f"{ORIGINALS_PREFIX}{map_id}/{image_id}/{IMAGE_NAME}"


def depth_key(map_id: str, image_id: str) -> str:
    """The key of a reference image's depth map as uploaded."""
    return f"{ORIGINALS_PREFIX}{map_id}/{image_id}/{DEPTH_NAME}"


def image_id_of(key: str) -> str | None:
    """The image id an originals key names, or None for a key of another shape."""
    parts = key.split("/")
    if len(parts) != 4 or f"{parts[0]}/" != ORIGINALS_PREFIX:
        return None
    if parts[3] not in (IMAGE_NAME, DEPTH_NAME):
        return None
    return parts[2]


def sha256_hex(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


@dataclass(frozen=True)
class StoredOriginals:
    """Where an image's originals were written: the image's key and SHA-256, and the depth
    map's key (None without depth)."""

    original_key: str
    original_sha256: str
    depth_key: str | None = None

    @property
    def keys(self) -> list[str]:
        return [k for k in (self.original_key, self.depth_key) if k is not None]


def write_originals(
    blobs: BlobStore,
    map_id: str,
    image_id: str,
    image_bytes: bytes,
    depth_bytes: bytes | None = None,
) -> StoredOriginals:
    """Write an image's originals (before its row is committed). A failure removes what may
    have been written (the puts tried: a failed one may still have stored its value) and
    raises the store's error (:class:`~db.blobs.BlobStoreError` when the store cannot be
    reached or refuses the write)."""
    stored = StoredOriginals(
        original_key(map_id, image_id),
        sha256_hex(image_bytes),
        depth_key(map_id, image_id) if depth_bytes is not None else None,
    )
    tried: list[str] = []
    try:
        tried.append(stored.original_key)
        blobs.put(stored.original_key, image_bytes)
        if stored.depth_key is not None and depth_bytes is not None:
            tried.append(stored.depth_key)
            blobs.put(stored.depth_key, depth_bytes)
    except BaseException:
        remove_blobs(blobs, tried)
        raise
    return stored


def remove_blobs(blobs: BlobStore, keys: Iterable[str]) -> list[str]:
    """Delete ``keys``, logging (not raising) failures: a blob left behind has no row and
    the next sweep removes it. The keys that could not be deleted."""
    failed = []
    for key in keys:
        try:
            blobs.delete(key)
        except Exception as exc:
            logger.warning("blob %s not deleted (the next sweep removes it): %s", key, exc)
            failed.append(key)
    return failed


def read_original(blobs: BlobStore, key: str) -> bytes | None:
    """The blob under ``key``, or None (logged) when it is missing."""
    try:
        return blobs.get(key)
    except BlobNotFoundError:
        logger.error("blob %s is missing from %s though its row names it", key, blobs.description)
        return None


@dataclass
class SweepReport:
    """What a reconciliation found. ``orphans``: blobs without a row (``removed`` of them
    deleted; the others younger than the grace period, or a check only). ``missing``: keys
    named by rows but absent from the store, with their image ids."""

    store: str
    blobs: int = 0
    rows_with_originals: int = 0
    orphans: list[str] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)
    missing: list[tuple[str, str]] = field(default_factory=list)
    temporaries_removed: int = 0
    seconds: float = 0.0

    def summary(self) -> str:
        return (
            f"{self.store}: {self.blobs} blobs, {self.rows_with_originals} references with "
            f"originals; {len(self.orphans)} blobs without a row ({len(self.removed)} removed), "
            f"{len(self.missing)} blobs missing"
            + (
                f", {self.temporaries_removed} stale temporary files removed"
                if self.temporaries_removed
                else ""
            )
            + f" ({self.seconds:.1f} s)"
        )


def reconcile(
    sessions: sessionmaker[Session],
    blobs: BlobStore,
    grace_s: float,
    remove: bool = True,
) -> SweepReport:
    """Compare the originals in ``blobs`` with the rows that name them: with ``remove``,
    delete the blobs without a row last written more than ``grace_s`` seconds ago (and a
    folder store's stale temporary files); report the rows whose blobs are missing.

    Blobs are listed before the rows are read, so an add that commits meanwhile is seen with
    its row; a blob younger than the grace period may belong to an add not yet committed and
    is left alone.
    """
    start = time.perf_counter()
    report = SweepReport(blobs.description)
    cutoff = datetime.now(UTC) - timedelta(seconds=grace_s)
    listed: dict[str, BlobInfo] = {info.key: info for info in blobs.list(ORIGINALS_PREFIX)}
    report.blobs = len(listed)
    # blobs without a row: the rows of the image ids the keys name, a chunk at a time
    keys = sorted(listed)
    for begin in range(0, len(keys), _CHUNK):
        chunk = keys[begin : begin + _CHUNK]
        ids = {i for i in map(image_id_of, chunk) if i is not None}
        named = _keys_of_rows(sessions, ids)
        for key in chunk:
            if key in named:
                continue
            report.orphans.append(key)
            if remove and listed[key].modified <= cutoff and not remove_blobs(blobs, [key]):
                report.removed.append(key)
    if remove and isinstance(blobs, FileBlobStore):
        report.temporaries_removed = blobs.remove_stale_temporaries(grace_s)
    # rows whose blobs are missing: a key not listed is checked again (an add may have
    # written it and committed after the listing), as is the row (deleted meanwhile)
    suspects: list[tuple[str, str]] = []
    with sessions() as session:
        rows = session.execute(
            select(ReferenceImage.id, ReferenceImage.original_key, ReferenceImage.depth_key)
            .where(
                or_(ReferenceImage.original_key.is_not(None), ReferenceImage.depth_key.is_not(None))
            )
            .execution_options(yield_per=1000)
        )
        for image_id, image_key, depth in rows:
            report.rows_with_originals += 1
            suspects.extend((image_id, k) for k in (image_key, depth) if k and k not in listed)
    for image_id, key in suspects:
        if blobs.exists(key) or key not in _keys_of_rows(sessions, {image_id}):
            continue
        report.missing.append((image_id, key))
        logger.error(
            "reference %s: its blob %s is missing from %s", image_id, key, blobs.description
        )
    report.seconds = time.perf_counter() - start
    return report


def _keys_of_rows(sessions: sessionmaker[Session], image_ids: set[str]) -> set[str]:
    """The blob keys the rows of ``image_ids`` name: references, and the frames of capture
    sessions waiting to become references under the same ids."""
    if not image_ids:
        return set()
    with sessions() as session:
        rows = [
            *session.execute(
                select(ReferenceImage.original_key, ReferenceImage.depth_key).where(
                    ReferenceImage.id.in_(image_ids)
                )
            ),
            *session.execute(
                select(CaptureFrame.original_key, CaptureFrame.depth_key).where(
                    CaptureFrame.id.in_(image_ids)
                )
            ),
        ]
    return {key for row in rows for key in row if key is not None}
