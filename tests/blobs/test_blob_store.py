"""The blob store's port, on a folder and on a real S3 server (SeaweedFS): put, get, exists,
list, delete; keys checked; the S3 server refuses unknown keys; where the default folder is."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from db.blobs import (
    BlobNotFoundError,
    BlobStore,
    BlobStoreError,
    FileBlobStore,
    S3BlobStore,
    default_blob_folder,
    open_blob_store,
)
from tests.blobs.s3_server import SeaweedS3, s3_server  # noqa: F401


@pytest.fixture(params=["folder", "s3"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[BlobStore]:
    if request.param == "folder":
        yield FileBlobStore(tmp_path / "blobs")
        return
    server: SeaweedS3 = request.getfixturevalue("s3_server")
    yield S3BlobStore(server.new_bucket(), "tenant/slloc", client=server.client())


def test_put_get_exists_list_delete(store: BlobStore) -> None:
    before = datetime.now(UTC) - timedelta(seconds=5)
    payload = bytes(range(256)) * 1000
    store.put("originals/m/i1/image", payload)
    store.put("originals/m/i1/depth", b"depth")
    store.put("other/x", b"x")
    assert store.get("originals/m/i1/image") == payload
    assert store.exists("originals/m/i1/image")
    assert not store.exists("originals/m/i2/image")
    listed = {info.key: info for info in store.list("originals/")}
    assert set(listed) == {"originals/m/i1/image", "originals/m/i1/depth"}
    assert listed["originals/m/i1/image"].size == len(payload)
    modified = listed["originals/m/i1/image"].modified
    assert modified.tzinfo is not None
    assert before <= modified <= datetime.now(UTC) + timedelta(seconds=5)
    assert {info.key for info in store.list()} == {*listed, "other/x"}
    store.put("originals/m/i1/image", b"replaced")
    assert store.get("originals/m/i1/image") == b"replaced"
    store.delete("originals/m/i1/image")
    store.delete("originals/m/i1/image")  # deleting what is gone is no error
    assert not store.exists("originals/m/i1/image")
    with pytest.raises(BlobNotFoundError):
        store.get("originals/m/i1/image")
    assert {info.key for info in store.list("originals/")} == {"originals/m/i1/depth"}


@pytest.mark.parametrize("key", ["", "/abs", "a/../b", "a//b", ".hidden", "a/.tmp", "sp ace"])
def test_keys_are_checked(store: BlobStore, key: str) -> None:
    with pytest.raises(ValueError):
        store.put(key, b"x")


def test_s3_refuses_unknown_credentials(s3_server: SeaweedS3) -> None:  # noqa: F811
    bucket = s3_server.new_bucket()
    S3BlobStore(bucket, client=s3_server.client()).put("k", b"v")
    intruder = S3BlobStore(bucket, client=s3_server.client("nobody", "wrong-secret"))
    with pytest.raises(Exception, match=r"InvalidAccessKeyId|AccessDenied|SignatureDoesNotMatch"):
        intruder.get("k")
    with pytest.raises(BlobStoreError):
        intruder.check()


def test_s3_store_from_the_standard_environment(
    s3_server: SeaweedS3,  # noqa: F811
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """SLLOC_BLOB_URL=s3://bucket/prefix with the AWS_* variables of any S3 client."""
    bucket = s3_server.new_bucket()
    for name, value in s3_server.env().items():
        monkeypatch.setenv(name, value)
    store = open_blob_store(f"s3://{bucket}/a/b", "sqlite:///unused.db")
    assert isinstance(store, S3BlobStore)
    store.put("k", b"v")
    keys = [o["Key"] for o in s3_server.client().list_objects_v2(Bucket=bucket)["Contents"]]
    assert keys == ["a/b/k"]
    assert [info.key for info in store.list()] == ["k"]


def test_interrupted_folder_writes_are_not_listed_and_are_swept(tmp_path: Path) -> None:
    store = FileBlobStore(tmp_path)
    store.put("originals/m/i/image", b"whole")
    leftover = tmp_path / "originals/m/i/.depth.tmp-0123"  # a write killed before its rename
    leftover.write_bytes(b"par")
    old = time.time() - 7200
    os.utime(leftover, (old, old))
    assert [info.key for info in store.list()] == ["originals/m/i/image"]
    assert store.remove_stale_temporaries(3600) == 1
    assert not leftover.exists()
    assert store.get("originals/m/i/image") == b"whole"


def test_default_folder(tmp_path: Path) -> None:
    db = tmp_path / "data" / "slloc.db"
    assert default_blob_folder(f"sqlite:///{db}", None) == tmp_path / "data" / "slloc.db.blobs"
    assert default_blob_folder(f"sqlite:///{db}", tmp_path / "d") == tmp_path / "d" / "blobs"
    assert default_blob_folder("postgresql+psycopg://u@h/db", None) == Path("data/blobs")
    folder = open_blob_store(None, f"sqlite:///{db}")
    assert isinstance(folder, FileBlobStore) and folder.root == db.with_name("slloc.db.blobs")
    named = open_blob_store(f"file://{tmp_path / 'x'}", "sqlite:///unused.db")
    assert isinstance(named, FileBlobStore) and named.root == tmp_path / "x"
    with pytest.raises(BlobStoreError):
        open_blob_store("ftp://host/x", "sqlite:///unused.db")
    with pytest.raises(BlobStoreError):
        open_blob_store("s3:///prefix-without-bucket", "sqlite:///unused.db")
