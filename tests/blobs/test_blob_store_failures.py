"""A blob store that refuses writes or cannot be reached: an add answers 503
blob-store-unavailable with Retry-After and stores nothing (no row without its blob), a GET of
an original that cannot be read answers 503 and one whose blob is missing 404, reads and
localize keep answering, and adds succeed again once the store is back, without a restart.

The folder is made read-only with ``chattr +i`` (the tests run as root, whom ``chmod`` does
not stop; skipped where the attribute is unsupported); the S3 store is a real SeaweedFS server,
stopped under the running app."""

from __future__ import annotations

import contextlib
import json
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from db.blobs import BlobStore, BlobStoreError, FileBlobStore, S3BlobStore
from db.originals import original_key, reconcile
from tests.blobs.s3_server import SeaweedS3, start_or_skip
from tests.conftest import create_map, image_metadata, make_client
from tools.synthetic.scene import SyntheticView, encode_depth_png, encode_png

PROBLEM = "application/problem+json"
UNAVAILABLE = "https://slloc.dev/problems/blob-store-unavailable"


def _chattr(flag: str, *paths: Path) -> None:
    subprocess.run(["chattr", flag, *map(str, paths)], check=True, capture_output=True)


def _folders(root: Path) -> list[Path]:
    return [root, *(p for p in root.rglob("*") if p.is_dir())]


@contextlib.contextmanager
def _immutable(root: Path) -> Iterator[None]:
    """``root`` and every folder under it immutable (no file created, renamed or removed in
    them, by root too) for the block; skips the test where ``chattr +i`` is not supported."""
    if shutil.which("chattr") is None:
        pytest.skip("chattr is not installed")
    folders = _folders(root)
    try:
        _chattr("+i", *folders)
    except subprocess.CalledProcessError as exc:
        pytest.skip(f"chattr +i failed (needs CAP_LINUX_IMMUTABLE and ext4/xfs/btrfs): {exc}")
    try:
        yield
    finally:
        _chattr("-i", *folders)


def _add(
    client: TestClient, map_id: str, view: SyntheticView, name: str, depth: bool = False
) -> Any:
    files = {"image": (view.name, encode_png(view.image), "image/png")}
    if depth:
        files["depth"] = ("depth.png", encode_depth_png(view.depth), "image/png")
    return client.post(
        f"/v1/maps/{map_id}/images",
        files=files,
        data={"metadata": json.dumps(image_metadata(view, name))},
    )


def _assert_unavailable(response: Any, *, stored_nothing: bool) -> None:
    assert response.status_code == 503, response.text
    assert response.headers["content-type"] == PROBLEM
    assert response.headers["retry-after"] == "5"
    problem = response.json()
    assert problem["type"] == UNAVAILABLE
    assert problem["title"] == "Blob store unavailable"
    assert ("nothing was stored" in problem["detail"]) is stored_nothing


def _names(client: TestClient, map_id: str) -> list[str]:
    page = client.get(f"/v1/maps/{map_id}/images").json()
    return sorted(item["name"] for item in page["items"])


def _blobs(client: TestClient) -> BlobStore:
    blobs: BlobStore = client.app.state.blobs  # type: ignore[attr-defined]
    return blobs


def _health_says(client: TestClient, blob_store: str) -> None:
    """GET /v1/health, probing the store afresh, names ``blob_store``, degraded when it is
    unavailable; so does /readyz's text (the probe reused); a scrape of /metrics, probing it
    afresh too, says 1 or 0."""
    state = client.app.state  # type: ignore[attr-defined]
    state.blob_probe = None
    scraped = client.get("/metrics")
    assert scraped.status_code == 200
    assert f"\nslloc_blob_store_up {1.0 if blob_store == 'ok' else 0.0}\n" in scraped.text
    state.blob_probe = None
    health = client.get("/v1/health").json()
    assert health["blob_store"] == blob_store
    assert health["status"] == ("ok" if blob_store == "ok" else "degraded")
    ready = client.get("/readyz")  # ready either way: localize never needs the store
    assert ready.status_code == 200
    assert ready.text == (
        "ok\n" if blob_store == "ok" else "ok; degraded: blob store: unavailable; adds answer 503\n"
    )


def _localizes(client: TestClient, map_id: str, view: SyntheticView) -> None:
    response = client.post(
        f"/v1/maps/{map_id}/localize",
        files={"image": (view.name, encode_png(view.image), "image/png")},
        data={"params": json.dumps({"top_k": 8})},
    )
    assert response.status_code == 200, response.text


def test_a_read_only_blob_folder_refuses_adds_with_503_and_stores_nothing(
    database_url: str,
    localizer: Any,
    tmp_path: Path,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    with make_client(database_url, localizer, data_dir=tmp_path / "data") as client:
        map_id = create_map(client)
        for index, view in enumerate(reference_views[:3]):
            assert _add(client, map_id, view, f"kept-{index}").status_code == 201
        first = client.get(f"/v1/maps/{map_id}/images").json()["items"][0]
        blobs = _blobs(client)
        assert isinstance(blobs, FileBlobStore)
        before = sorted(info.key for info in blobs.list())

        _health_says(client, "ok")
        with _immutable(blobs.root):
            _health_says(client, "unavailable")
            for depth in (False, True):
                refused = _add(client, map_id, reference_views[4], "refused", depth=depth)
                _assert_unavailable(refused, stored_nothing=True)
                assert "cannot write" not in refused.json()["detail"]  # no path leaked
            # reads and localize go on
            assert _names(client, map_id) == ["kept-0", "kept-1", "kept-2"]
            original = client.get(f"/v1/maps/{map_id}/images/{first['id']}/original")
            assert original.status_code == 200
            assert original.headers["etag"] == f'"{first["original_sha256"]}"'
            _localizes(client, map_id, query_views[0])
            # no blob and no temporary file left behind
            assert sorted(info.key for info in blobs.list()) == before
            assert not [p for p in blobs.root.rglob(".*") if p.is_file()]

        # writable again: the same add succeeds, without a restart
        _health_says(client, "ok")
        assert _add(client, map_id, reference_views[4], "refused", depth=True).status_code == 201
        assert _names(client, map_id) == ["kept-0", "kept-1", "kept-2", "refused"]
        sessions = client.app.state.sessions  # type: ignore[attr-defined]
        report = reconcile(sessions, blobs, 0.0, remove=False)
        assert (report.orphans, report.missing, report.rows_with_originals) == ([], [], 4)


def test_a_file_store_maps_file_system_refusals_to_blob_store_errors(tmp_path: Path) -> None:
    """The folder store raises BlobStoreError, naming the key and the reason, for a write
    the file system refuses, and for a read of a key that is a folder."""
    store = FileBlobStore(tmp_path / "blobs")
    store.put("a/b", b"x")
    store.check()
    with _immutable(store.root):
        with pytest.raises(BlobStoreError, match="not writable"):
            store.check()
        with pytest.raises(BlobStoreError, match=r"cannot write c/d: Operation not permitted"):
            store.put("c/d", b"y")
        with pytest.raises(BlobStoreError, match="cannot delete a/b"):
            store.delete("a/b")
        assert store.get("a/b") == b"x"
    with pytest.raises(BlobStoreError, match="cannot read a: Is a directory"):
        store.get("a")
    shutil.rmtree(store.root)
    with pytest.raises(BlobStoreError, match="not a folder"):
        store.check()


def test_a_missing_blob_answers_a_404_that_says_so(
    database_url: str, localizer: Any, tmp_path: Path, reference_views: list[SyntheticView]
) -> None:
    with make_client(database_url, localizer, data_dir=tmp_path / "data") as client:
        map_id = create_map(client)
        image = _add(client, map_id, reference_views[0], "lost").json()
        _blobs(client).delete(original_key(map_id, image["id"]))
        response = client.get(f"/v1/maps/{map_id}/images/{image['id']}/original")
        assert response.status_code == 404
        assert response.headers["content-type"] == PROBLEM
        assert "missing from the blob store" in response.json()["detail"]


@pytest.fixture
def own_s3_server(tmp_path: Path) -> Iterator[SeaweedS3]:
    """A SeaweedFS server of this test's own: the test stops it."""
    with start_or_skip(tmp_path / "seaweedfs") as server:
        yield server


def test_an_unreachable_s3_store_answers_503_and_stores_nothing(
    database_url: str,
    localizer: Any,
    own_s3_server: SeaweedS3,
    monkeypatch: pytest.MonkeyPatch,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    for name, value in own_s3_server.env().items():
        monkeypatch.setenv(name, value)
    bucket = own_s3_server.new_bucket()
    with make_client(database_url, localizer, blob_url=f"s3://{bucket}/slloc") as client:
        blobs = _blobs(client)
        assert isinstance(blobs, S3BlobStore)
        # the server's own client: 2 attempts instead of the default 5 with backoff, so the
        # test does not wait out retries (the store is the same)
        blobs.client = own_s3_server.client()
        map_id = create_map(client)
        kept = [
            _add(client, map_id, view, f"kept-{i}").json()
            for i, view in enumerate(reference_views[:3])
        ]
        assert all("id" in image for image in kept)

        _health_says(client, "ok")
        own_s3_server.close()
        _health_says(client, "unavailable")
        refused = _add(client, map_id, reference_views[4], "refused", depth=True)
        _assert_unavailable(refused, stored_nothing=True)
        assert _names(client, map_id) == ["kept-0", "kept-1", "kept-2"]
        unread = client.get(f"/v1/maps/{map_id}/images/{kept[0]['id']}/original")
        _assert_unavailable(unread, stored_nothing=False)
        # localize never reads the blobs; a delete removes the row and leaves the blob to
        # the sweep
        _localizes(client, map_id, query_views[0])
        assert client.delete(f"/v1/maps/{map_id}/images/{kept[2]['id']}").status_code == 204
        assert _names(client, map_id) == ["kept-0", "kept-1"]
