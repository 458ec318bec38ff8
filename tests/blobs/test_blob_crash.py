"""Rows and blobs stay consistent across ``kill -9``: a real ``slloc serve`` is killed with
SIGKILL while clients add and delete references, several times over. Right after the kills no
row lacks its blob (blobs are written before the row commits, deleted after its deletion
commits); the blobs without a row that the kills left are removed by the next start-up's sweep,
after which there are 0 orphans and 0 missing. On the default folder store and on a real S3
server (SeaweedFS)."""

from __future__ import annotations

import hashlib
import json
import os
import random
import signal
import threading
import uuid
from pathlib import Path

import httpx
import pytest
from sqlalchemy import select

from db.blobs import BlobStore, FileBlobStore, S3BlobStore
from db.models import ReferenceImage
from db.originals import original_key, reconcile
from db.session import make_engine, make_session_factory
from services.features.configs import SIFT
from tests.blobs.s3_server import SeaweedS3, s3_server  # noqa: F401
from tests.conftest import image_metadata
from tests.polling import wait_until
from tools.evaluation.server import LocalServer
from tools.synthetic.scene import SyntheticView, encode_png

CYCLES = 3
WORKERS = 3


def _client_loop(
    url: str,
    map_id: str,
    uploads: list[tuple[dict[str, object], bytes]],
    stop: threading.Event,
    counts: dict[str, int],
    lock: threading.Lock,
) -> None:
    """Adds references and deletes about every other one it added, until the server dies."""
    rng = random.Random()
    added: list[str] = []
    with httpx.Client(base_url=url, timeout=60) as http:
        while not stop.is_set():
            try:
                if added and rng.random() < 0.5:
                    image_id = added.pop(rng.randrange(len(added)))
                    http.delete(f"/v1/maps/{map_id}/images/{image_id}")
                    with lock:
                        counts["deletes"] += 1
                    continue
                metadata, png = rng.choice(uploads)
                metadata = {**metadata, "name": f"r-{uuid.uuid4().hex}"}
                response = http.post(
                    f"/v1/maps/{map_id}/images",
                    files={"image": ("r.png", png, "image/png")},
                    data={"metadata": json.dumps(metadata)},
                )
                if response.status_code == 201:
                    added.append(response.json()["id"])
                    with lock:
                        counts["adds"] += 1
            except httpx.TransportError:  # killed
                return


def _store(
    kind: str, tmp_path: Path, request: pytest.FixtureRequest
) -> tuple[dict[str, str], BlobStore]:
    env = {
        "SLLOC_DATABASE_URL": f"sqlite:///{tmp_path / 'slloc.db'}",
        "SLLOC_FEATURES": SIFT,
        "SLLOC_MODELS_DIR": "/nonexistent-models",
        "SLLOC_LOCALIZE_WORKERS": "2",
    }
    if kind == "folder":
        return env, FileBlobStore(tmp_path / "slloc.db.blobs")
    server: SeaweedS3 = request.getfixturevalue("s3_server")
    bucket = server.new_bucket()
    env |= server.env() | {"SLLOC_BLOB_URL": f"s3://{bucket}/slloc"}
    return env, S3BlobStore(bucket, "slloc", client=server.client())


@pytest.mark.parametrize("kind", ["folder", "s3"])
def test_kill_9_during_adds_and_deletes(
    kind: str,
    tmp_path: Path,
    request: pytest.FixtureRequest,
    reference_views: list[SyntheticView],
) -> None:
    env, blobs = _store(kind, tmp_path, request)
    uploads = [(image_metadata(v), encode_png(v.image)) for v in reference_views[:6]]
    counts = {"adds": 0, "deletes": 0}
    lock = threading.Lock()
    rng = random.Random(7)
    map_id = None
    for _ in range(CYCLES):
        with LocalServer(env) as server:
            if map_id is None:
                created = httpx.post(f"{server.url}/v1/maps", json={"name": "crash"}, timeout=30)
                assert created.status_code == 201, created.text
                map_id = created.json()["id"]
            stop = threading.Event()
            threads = [
                threading.Thread(
                    target=_client_loop, args=(server.url, map_id, uploads, stop, counts, lock)
                )
                for _ in range(WORKERS)
            ]
            with lock:
                before = dict(counts)
            for thread in threads:
                thread.start()
            # killed while the clients are at work: once this cycle has seen adds and deletes
            # answered (a random number of adds, so the kill lands at another point of the
            # stream each time), the other clients' requests are in flight
            adds = rng.randint(2, 5)

            def at_work(adds: int = adds, before: dict[str, int] = before) -> bool:
                with lock:
                    return (
                        counts["adds"] - before["adds"] >= adds
                        and counts["deletes"] > before["deletes"]
                    )

            assert wait_until(at_work, 300), counts
            os.kill(server.pid, signal.SIGKILL)
            server.process.wait(timeout=30)
            stop.set()
            for thread in threads:
                thread.join(timeout=90)
    assert counts["adds"] > 0 and counts["deletes"] > 0, counts

    engine = make_engine(env["SLLOC_DATABASE_URL"])
    sessions = make_session_factory(engine)
    # right after the kills: orphans may be there, never a row without its blob
    after_kills = reconcile(sessions, blobs, 0.0, remove=False)
    assert after_kills.missing == []
    with sessions() as session:
        rows = session.execute(select(ReferenceImage.original_key)).all()
    assert rows and all(key is not None for (key,) in rows)

    # a kill rarely lands in the milliseconds between a blob's write and its row's commit:
    # leave what it leaves there too, blobs of an add whose row never committed
    planted = [original_key(map_id, str(uuid.uuid4())) for _ in range(3)]
    for key in planted:
        blobs.put(key, b"an add killed before its commit")
    # the next start sweeps (grace 0 here: no add is running)
    with LocalServer(env | {"SLLOC_BLOB_SWEEP_GRACE_S": "0"}, log_level="info") as server:
        swept = wait_until(lambda: "blob sweep:" in server.log_text(), 60)
        assert swept, server.log_text()[-3000:]
    report = reconcile(sessions, blobs, 0.0, remove=False)
    print(
        f"{kind}: {counts['adds']} adds, {counts['deletes']} deletes in {CYCLES} kills; "
        f"{len(after_kills.orphans)} orphans after them (+{len(planted)} planted); then "
        f"{report.summary()}"
    )
    assert not any(blobs.exists(key) for key in planted)
    assert (report.orphans, report.missing) == ([], [])
    assert report.blobs == report.rows_with_originals == len(rows)
    with sessions() as session:
        for key, sha256 in session.execute(
            select(ReferenceImage.original_key, ReferenceImage.original_sha256)
        ):
            assert hashlib.sha256(blobs.get(key)).hexdigest() == sha256
    engine.dispose()
