"""The blob store: where the originals of reference images (the image bytes as uploaded, and
their depth maps) are kept, behind one small port.

Two stores implement :class:`BlobStore`: :class:`FileBlobStore` (a folder: beside the SQLite
file by default, or under ``SLLOC_DATA_DIR``) and :class:`S3BlobStore` (an S3-compatible object
store, ``SLLOC_BLOB_URL=s3://bucket/prefix``, shared by replicas). :func:`open_blob_store`
picks one from the settings' values.

Keys are relative paths of ``[A-Za-z0-9._-]`` segments joined by ``/``. A ``put`` is atomic:
a reader sees the whole value or no value, never a part (the folder writes a temporary file,
syncs it and renames it; an S3 PUT is atomic). Consistency with the database rows is kept by
the callers and the sweep (``db/blob_sweep.py``): write the blob before the row commits, delete
it after the row's deletion commits.
"""

from __future__ import annotations

import contextlib
import os
import re
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol
from urllib.parse import urlparse

from sqlalchemy.engine import make_url

_SEGMENT = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]*")
# what a folder store's writes in progress are named (never listed; the sweep removes stale
# ones)
_TEMPORARY_MARK = ".tmp-"


class BlobNotFoundError(KeyError):
    """No blob under the key."""


class BlobStoreError(RuntimeError):
    """The store could not be opened, could not be reached, or refused a read or a write (a
    read-only or full folder, an S3 endpoint down or answering with an error)."""


@dataclass(frozen=True)
class BlobInfo:
    """A stored blob: its key, its size in bytes and when it was last written (UTC)."""

    key: str
    size: int
    modified: datetime


class BlobStore(Protocol):
    """Where the blobs are kept. Every method raises :class:`BlobStoreError` when the store
    cannot be reached or refuses the operation (never the backend's own error)."""

    @property
    def description(self) -> str:
        """Where the store is, for logs and reports (no secret in it)."""
        ...

    def put(self, key: str, data: bytes) -> None:
        """Store ``data`` under ``key`` (replacing any value), atomically and durably: once
        it returns, the blob survives a crash of this process."""
        ...

    def get(self, key: str) -> bytes:
        """The value under ``key``.

        Raises:
            BlobNotFoundError: nothing is stored under ``key``.
        """
        ...

    def delete(self, key: str) -> None:
        """Remove the value under ``key``; nothing happens when there is none."""
        ...

    def exists(self, key: str) -> bool:
        """Whether a value is stored under ``key``."""
        ...

    def list(self, prefix: str = "") -> Iterator[BlobInfo]:
        """The blobs whose keys start with ``prefix``, in no particular order."""
        ...

    def check(self) -> None:
        """Nothing when the store can take writes now.

        Raises:
            BlobStoreError: it cannot (a folder missing or read-only; a bucket that cannot
                be reached, or refuses these credentials), saying why.
        """
        ...


def check_key(key: str) -> str:
    """``key`` when it is a valid key: ``/``-separated segments of letters, digits, ``.``,
    ``_`` and ``-``, none starting with ``.``.

    Raises:
        ValueError: it is not.
    """
    if not key or not all(_SEGMENT.fullmatch(part) for part in key.split("/")):
        raise ValueError(f"invalid blob key {key!r}")
    return key


class FileBlobStore:
    """Blobs as files under ``root`` (created when missing), one file per key."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)

    @property
    def description(self) -> str:
        return f"folder {self.root}"

    def _path(self, key: str) -> Path:
        return self.root / check_key(key)

    def put(self, key: str, data: bytes) -> None:
        path = self._path(key)
        temporary = path.with_name(f".{path.name}{_TEMPORARY_MARK}{uuid.uuid4().hex}")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with open(temporary, "wb") as file:
                file.write(data)
                file.flush()
                os.fsync(file.fileno())
            os.replace(temporary, path)
        except BaseException as exc:
            with contextlib.suppress(OSError):  # a read-only folder refuses this too
                temporary.unlink(missing_ok=True)
            if isinstance(exc, OSError):
                raise self._failed("write", key, exc) from exc
            raise
        _sync_directory(path.parent)

    def get(self, key: str) -> bytes:
        try:
            return self._path(key).read_bytes()
        except (FileNotFoundError, NotADirectoryError):
            raise BlobNotFoundError(key) from None
        except OSError as exc:
            raise self._failed("read", key, exc) from exc

    def delete(self, key: str) -> None:
        path = self._path(key)
        try:
            path.unlink()
        except (FileNotFoundError, NotADirectoryError):
            return
        except OSError as exc:
            raise self._failed("delete", key, exc) from exc
        _sync_directory(path.parent)

    def _failed(self, action: str, key: str, exc: OSError) -> BlobStoreError:
        """The error of an ``action`` on ``key`` that the file system refused: a read-only
        folder or file system (EROFS, or EPERM for an immutable folder), a full disk
        (ENOSPC), no permission (EACCES), an I/O error."""
        reason = exc.strerror or str(exc)
        return BlobStoreError(f"{self.description}: cannot {action} {key}: {reason}")

    def exists(self, key: str) -> bool:
        return self._path(key).is_file()

    def list(self, prefix: str = "") -> Iterator[BlobInfo]:
        for directory, dirs, files in os.walk(self.root):
            dirs[:] = [d for d in dirs if not d.startswith(".")]
            base = Path(directory).relative_to(self.root)
            for name in files:
                if name.startswith("."):
                    continue
                key = (base / name).as_posix()
                if not key.startswith(prefix):
                    continue
                try:
                    stat = (Path(directory) / name).stat()
                except FileNotFoundError:  # deleted while listed
                    continue
                yield BlobInfo(key, stat.st_size, datetime.fromtimestamp(stat.st_mtime, UTC))

    def check(self) -> None:
        # access(2) also answers no for a read-only file system and an immutable folder
        if not self.root.is_dir():
            raise BlobStoreError(f"{self.description}: not a folder")
        if not os.access(self.root, os.W_OK | os.X_OK):
            raise BlobStoreError(f"{self.description}: not writable")

    def remove_stale_temporaries(self, older_than_s: float) -> int:
        """Remove the temporary files of writes that a crash interrupted, older than
        ``older_than_s`` seconds; the number removed."""
        removed = 0
        cutoff = time.time() - older_than_s
        for directory, _dirs, files in os.walk(self.root):
            for name in files:
                if not (name.startswith(".") and _TEMPORARY_MARK in name):
                    continue
                path = Path(directory) / name
                try:
                    if path.stat().st_mtime <= cutoff:
                        path.unlink()
                        removed += 1
                except FileNotFoundError:
                    continue
        return removed


def _sync_directory(directory: Path) -> None:
    """Make a rename or unlink in ``directory`` durable (a no-op where directories cannot be
    opened)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class S3BlobStore:
    """Blobs as objects of an S3-compatible store under ``bucket``/``prefix``. Credentials,
    region and endpoint come from boto3's standard chain (``AWS_ACCESS_KEY_ID``,
    ``AWS_SECRET_ACCESS_KEY``, ``AWS_REGION``, ``AWS_ENDPOINT_URL`` …), or ``client``."""

    def __init__(self, bucket: str, prefix: str = "", client: Any = None) -> None:
        if not bucket:
            raise BlobStoreError("an s3:// blob URL needs a bucket: s3://bucket/prefix")
        self.bucket = bucket
        self.prefix = prefix.strip("/")
        if self.prefix:
            check_key(self.prefix)
        self.client = client if client is not None else _s3_client()

    @property
    def description(self) -> str:
        endpoint = getattr(getattr(self.client, "meta", None), "endpoint_url", None)
        where = f"s3://{self.bucket}/{self.prefix}".rstrip("/")
        return f"{where} at {endpoint}" if endpoint else where

    def _name(self, key: str) -> str:
        check_key(key)
        return f"{self.prefix}/{key}" if self.prefix else key

    def put(self, key: str, data: bytes) -> None:
        name = self._name(key)
        try:
            self.client.put_object(Bucket=self.bucket, Key=name, Body=data)
        except _s3_failures() as exc:
            raise self._failed("write", key, exc) from exc

    def get(self, key: str) -> bytes:
        name = self._name(key)
        try:
            response = self.client.get_object(Bucket=self.bucket, Key=name)
            body: bytes = response["Body"].read()
        except _s3_failures() as exc:
            if _not_found(exc):
                raise BlobNotFoundError(key) from None
            raise self._failed("read", key, exc) from exc
        return body

    def delete(self, key: str) -> None:
        name = self._name(key)
        try:
            self.client.delete_object(Bucket=self.bucket, Key=name)
        except _s3_failures() as exc:
            raise self._failed("delete", key, exc) from exc

    def exists(self, key: str) -> bool:
        name = self._name(key)
        try:
            self.client.head_object(Bucket=self.bucket, Key=name)
        except _s3_failures() as exc:
            if _not_found(exc):
                return False
            raise self._failed("check", key, exc) from exc
        return True

    def list(self, prefix: str = "") -> Iterator[BlobInfo]:
        base = f"{self.prefix}/" if self.prefix else ""
        try:
            pages = self.client.get_paginator("list_objects_v2").paginate(
                Bucket=self.bucket, Prefix=base + prefix
            )
            for page in pages:
                for item in page.get("Contents", ()):
                    modified: datetime = item["LastModified"]
                    yield BlobInfo(
                        item["Key"][len(base) :], int(item["Size"]), modified.astimezone(UTC)
                    )
        except _s3_failures() as exc:
            raise self._failed("list", prefix or "the blobs", exc) from exc

    def _failed(self, action: str, key: str, exc: Exception) -> BlobStoreError:
        """The error of an ``action`` on ``key`` that failed: the endpoint unreachable or
        timing out, or an error answer (access denied, no such bucket, a 5xx)."""
        return BlobStoreError(f"{self.description}: cannot {action} {key}: {exc}")

    def check(self) -> None:
        try:
            self.client.head_bucket(Bucket=self.bucket)
        except Exception as exc:
            raise BlobStoreError(f"{self.description}: {exc}") from exc


def _s3_failures() -> tuple[type[Exception], ...]:
    """The errors of a failed S3 call: botocore's (connection, timeout, an error answer)."""
    try:
        from botocore.exceptions import BotoCoreError, ClientError
    except ImportError:  # pragma: no cover - a client of another library, passed in
        return ()
    return (BotoCoreError, ClientError)


def _not_found(exc: Exception) -> bool:
    response = getattr(exc, "response", None)
    if not isinstance(response, dict):
        return False
    code = str(response.get("Error", {}).get("Code", ""))
    return code in ("404", "NoSuchKey", "NotFound")


def _s3_client() -> Any:
    """A boto3 S3 client from the standard environment; path-style addressing when an
    endpoint is set (S3-compatible stores such as SeaweedFS or MinIO), with standard
    retries."""
    import boto3
    from botocore.config import Config

    endpoint = os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL")
    config = Config(
        s3={"addressing_style": "path" if endpoint else "auto"},
        retries={"mode": "standard", "max_attempts": 5},
        connect_timeout=10,
        read_timeout=60,
    )
    return boto3.client("s3", config=config)


def default_blob_folder(database_url: str, data_dir: Path | None) -> Path:
    """The folder store's place when no blob URL is set: ``data_dir``/blobs, else beside a
    SQLite file (``<file>.blobs``), else ``./data/blobs``."""
    if data_dir is not None:
        return Path(data_dir) / "blobs"
    url = make_url(database_url)
    if url.get_backend_name() == "sqlite" and url.database and url.database != ":memory:":
        path = Path(url.database)
        return path.with_name(f"{path.name}.blobs")
    return Path("data") / "blobs"


def open_blob_store(
    blob_url: str | None, database_url: str, data_dir: Path | None = None
) -> BlobStore:
    """The store ``blob_url`` names (``s3://bucket/prefix``, ``file:///path`` or a plain
    path), or without one the folder of :func:`default_blob_folder`.

    Raises:
        BlobStoreError: an unknown scheme, or an s3 URL without a bucket.
    """
    if not blob_url:
        return FileBlobStore(default_blob_folder(database_url, data_dir))
    parsed = urlparse(blob_url)
    if parsed.scheme == "s3":
        return S3BlobStore(parsed.netloc, parsed.path)
    if parsed.scheme == "file":
        return FileBlobStore(Path(parsed.path))
    if parsed.scheme == "":
        return FileBlobStore(Path(blob_url))
    raise BlobStoreError(f"SLLOC_BLOB_URL: unknown scheme {parsed.scheme!r} (s3:// or file://)")
