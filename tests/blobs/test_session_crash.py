"""A capture session survives ``kill -9``: a real ``slloc serve`` is killed with SIGKILL while
it adds a session's frames to the map; the next start resumes the session, which ends with
every frame added exactly once, no frame left waiting, and every blob with exactly one row."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import httpx
from sqlalchemy import func, select

from db.blobs import FileBlobStore
from db.models import CaptureFrame, ReferenceImage
from db.originals import reconcile
from db.session import make_engine, make_session_factory
from services.features.configs import SIFT
from tests.conftest import image_metadata
from tests.polling import wait_until
from tools.evaluation.server import LocalServer
from tools.synthetic.scene import SyntheticView, encode_png


def _upload_frame(http: httpx.Client, map_id: str, session_id: str, view: SyntheticView) -> None:
    metadata = image_metadata(view)
    metadata["cam_from_session"] = metadata.pop("cam_from_world")
    response = http.post(
        f"/v1/maps/{map_id}/sessions/{session_id}/frames",
        files={"image": (view.name, encode_png(view.image), "image/png")},
        data={"metadata": json.dumps(metadata)},
    )
    assert response.status_code == 201, response.text


def test_kill_9_while_a_session_is_added_resumes_it(
    tmp_path: Path, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    env = {
        "SLLOC_DATABASE_URL": f"sqlite:///{tmp_path / 'slloc.db'}",
        "SLLOC_FEATURES": SIFT,
        "SLLOC_MODELS_DIR": "/nonexistent-models",
        "SLLOC_LOCALIZE_WORKERS": "2",
    }
    mapped, captured = reference_views[:12], [*reference_views[12:], *query_views]
    with LocalServer(env) as server, httpx.Client(base_url=server.url, timeout=60) as http:
        map_id = http.post("/v1/maps", json={"name": "crash"}).json()["id"]
        for view in mapped:
            response = http.post(
                f"/v1/maps/{map_id}/images",
                files={"image": (view.name, encode_png(view.image), "image/png")},
                data={"metadata": json.dumps(image_metadata(view))},
            )
            assert response.status_code == 201, response.text
        # the session's frame is the map's: the frames carry their true poses
        session_id = http.post(
            f"/v1/maps/{map_id}/sessions", json={"name": "s", "keep_all": True}
        ).json()["id"]
        for view in captured:
            _upload_frame(http, map_id, session_id, view)
        assert http.post(f"/v1/maps/{map_id}/sessions/{session_id}/submit").status_code == 202
        url = f"/v1/maps/{map_id}/sessions/{session_id}"

        def adding() -> bool:
            body = http.get(url).json()
            if body["state"] in ("queued", "aligning"):
                return False
            added = body["progress"]["done"] - len(body["alignment"]["checked"])
            return body["state"] != "adding" or added >= 2

        assert wait_until(adding, 240, interval_s=0.02)
        at_kill = http.get(url).json()
        os.kill(server.pid, signal.SIGKILL)
        server.process.wait(timeout=30)
    assert at_kill["state"] == "adding", at_kill  # killed half-way through the adds

    with LocalServer(env) as server, httpx.Client(base_url=server.url, timeout=60) as http:

        def ended() -> bool:
            return bool(http.get(url).json()["state"] in ("added", "refused", "failed"))

        assert wait_until(ended, 240)
        session = http.get(url).json()
        images = http.get(f"/v1/maps/{map_id}/images", params={"limit": 1000}).json()["items"]
    assert session["state"] == "added", session
    assert session["alignment"]["added"] == len(captured)
    names = sorted(image["name"] for image in images)
    assert names == sorted([v.name for v in mapped] + [f"s/{v.name}" for v in captured])

    engine = make_engine(env["SLLOC_DATABASE_URL"])
    sessions = make_session_factory(engine)
    with sessions() as db:
        assert db.scalar(select(func.count()).select_from(CaptureFrame)) == 0
        assert db.scalar(select(func.count()).select_from(ReferenceImage)) == len(names)
    report = reconcile(sessions, FileBlobStore(tmp_path / "slloc.db.blobs"), 0.0, remove=False)
    assert (report.orphans, report.missing) == ([], [])
    assert report.blobs == report.rows_with_originals == len(names)
    engine.dispose()
