"""A SQLite database whose folder and files turn read-only under a running ``slloc serve``:
writes answer 503 database-not-writable with Retry-After (never a 500), reads and localize
keep answering, /readyz stays ready and says the database is not writable, and writes
succeed again once the files are writable, without a restart.

The files are made immutable (``chattr +i``), not ``chmod``-ed: the server's pooled SQLite
connections hold the files open, and a mode only stops later ``open()`` calls (and none at
all for root), whereas the kernel refuses every write to an immutable file, through open
descriptors too, as it does on a file system remounted read-only. That needs
CAP_LINUX_IMMUTABLE and a file system with the attribute (ext4, xfs, btrfs): skipped
elsewhere."""

from __future__ import annotations

import contextlib
import json
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.conftest import create_map, image_metadata
from tools.evaluation.server import LocalServer
from tools.synthetic.scene import SyntheticView, encode_png

PROBLEM = "application/problem+json"


def _chattr(flag: str, *paths: Path) -> None:
    subprocess.run(["chattr", flag, *map(str, paths)], check=True, capture_output=True)


def _immutable_refuses_open_files(folder: Path) -> str | None:
    """None where an immutable file refuses a write through a descriptor opened before;
    else why this test cannot run here."""
    if shutil.which("chattr") is None:
        return "chattr is not installed"
    probe = folder / "probe"
    with open(probe, "wb") as file:
        try:
            _chattr("+i", probe)
        except subprocess.CalledProcessError as exc:
            return f"chattr +i failed (needs CAP_LINUX_IMMUTABLE and ext4/xfs/btrfs): {exc.stderr}"
        try:
            file.write(b"x")
            file.flush()
        except OSError:
            return None
        finally:
            _chattr("-i", probe)
    return "an immutable file still accepted a write through an open descriptor"


@pytest.fixture
def folder(tmp_path: Path) -> Iterator[Path]:
    folder = tmp_path / "db"
    folder.mkdir()
    reason = _immutable_refuses_open_files(folder)
    if reason is not None:
        pytest.skip(reason)
    yield folder
    # never leave an immutable file behind: tmp_path could not be removed
    with contextlib.suppress(subprocess.CalledProcessError):
        _chattr("-i", folder, *folder.iterdir())


def _add(client: httpx.Client, map_id: str, view: SyntheticView, name: str) -> httpx.Response:
    return client.post(
        f"/v1/maps/{map_id}/images",
        files={"image": (view.name, encode_png(view.image), "image/png")},
        data={"metadata": json.dumps(image_metadata(view, name))},
    )


def _localize(client: httpx.Client, map_id: str, view: SyntheticView) -> httpx.Response:
    return client.post(
        f"/v1/maps/{map_id}/localize",
        files={"image": (view.name, encode_png(view.image), "image/png")},
        data={"params": json.dumps({"top_k": 8})},
    )


def _assert_not_writable(response: httpx.Response) -> None:
    assert response.status_code == 503, response.text
    assert response.headers["content-type"] == PROBLEM
    assert int(response.headers["retry-after"]) > 0
    problem = response.json()
    assert problem["type"].endswith("/database-not-writable"), problem
    assert problem["status"] == 503 and "writ" in problem["detail"], problem
    assert problem["instance"] == response.request.url.path


def test_read_only_database_refuses_writes_serves_reads_and_recovers(
    folder: Path, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    database = folder / "slloc.db"
    env = {
        "SLLOC_DATABASE_URL": f"sqlite:///{database}",
        "SLLOC_FEATURES": "sift",
        "SLLOC_MODELS_DIR": "/nonexistent-models",
    }
    with LocalServer(env) as server, httpx.Client(base_url=server.url, timeout=60) as client:
        map_id = create_map(client)  # type: ignore[arg-type]
        ids = []
        for i, view in enumerate(reference_views[:6]):
            response = _add(client, map_id, view, f"r{i}")
            assert response.status_code == 201, response.text
            ids.append(response.json()["id"])
        localized = _localize(client, map_id, query_views[0])
        assert localized.status_code == 200 and localized.json()["localized"], localized.text
        assert client.get("/readyz").text == "ok\n"

        # the folder and every file of the database; the originals' folder (a subfolder)
        # stays writable, so that an add reaches the database
        frozen = [folder, *(p for p in folder.iterdir() if p.is_file())]
        assert {p.name for p in frozen} >= {"db", "slloc.db", "slloc.db-wal", "slloc.db-shm"}
        _chattr("+i", *frozen)
        try:
            writes = [
                client.post("/v1/maps", json={"name": "frozen"}),
                _add(client, map_id, reference_views[6], "frozen"),
                client.delete(f"/v1/maps/{map_id}/images/{ids[0]}"),
                client.post("/v1/maps", json={"name": "frozen again"}),
            ]
            for response in writes:
                _assert_not_writable(response)
            # reads, localize included, are still served
            listed = client.get("/v1/maps")
            assert listed.status_code == 200 and listed.json()["total"] == 1, listed.text
            images = client.get(f"/v1/maps/{map_id}/images")
            assert images.status_code == 200 and images.json()["total"] == 6, images.text
            localized = _localize(client, map_id, query_views[1])
            assert localized.status_code == 200 and localized.json()["localized"], localized.text
            ready = client.get("/readyz")
            assert ready.status_code == 200 and "not writable" in ready.text, ready.text
            assert client.get("/livez").status_code == 200
        finally:
            _chattr("-i", *frozen)

        # writable again: the same process writes at once and /readyz is plain ok
        created = client.post("/v1/maps", json={"name": "thawed"})
        assert created.status_code == 201, created.text
        added = _add(client, map_id, reference_views[6], "thawed")
        assert added.status_code == 201, added.text
        assert client.get("/readyz").text == "ok\n"
        names = {m["name"] for m in client.get("/v1/maps").json()["items"]}
        assert names == {"scene", "thawed"}, names
        assert client.get(f"/v1/maps/{map_id}/images").json()["total"] == 7
        assert server.process.poll() is None  # never restarted
        log = server.log_text()
        assert "unhandled error" not in log, log
        assert " 500 " not in log
        refused = sorted(
            {line.rsplit(": ", 1)[-1] for line in log.splitlines() if "not writable" in line}
        )
        print(f"\n{len(writes)} writes refused with 503 while read-only; SQLite said {refused}")
