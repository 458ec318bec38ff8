"""The Python SDK (clients/python, installed by ``scripts/setup.sh dev``) against a live
``slloc serve``: the README's demo flow (create a map, upload the references with their
metadata, localize a query, check the pose against the ground truth), problems as exceptions,
and ``Retry-After`` against a real HTTP server answering 503."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
from slloc_client import Client, ProblemError
from slloc_client.models import LocalizeResult

from tests.clients.conftest import assert_near_truth, ground_truth
from tools.evaluation.server import LocalServer


def test_upload_references_and_localize_the_demo_query(
    live_server: LocalServer, demo: Path
) -> None:
    with Client(live_server.url) as slloc:
        health = slloc.health()
        assert health.status in {"ok", "degraded"}
        # the server's own configuration by name: the map does not evaluate itself as it grows
        served = health.models.feature_configurations[0]
        demo_map = slloc.create_map(
            "python-client", description="the demo scene", features={"preset": served}
        )
        assert (demo_map.features.preset, demo_map.features.auto) == (served, False)
        metas = sorted((demo / "references").glob("*.json"))
        first = json.loads(metas[0].read_text())
        added = slloc.add_image(
            demo_map.id,
            metas[0].with_suffix(".png").read_bytes(),
            name=first["name"],
            camera=first["camera"],
            cam_from_world=first["cam_from_world"],
        )
        assert added.name == first["name"]
        for meta in metas[1:]:
            slloc.add_image_metadata(
                demo_map.id, meta.with_suffix(".png"), json.loads(meta.read_text())
            )
        assert slloc.get_map(demo_map.id).image_count == len(metas)
        changed = slloc.update_map(demo_map.id, description="kitchen", default_estimator="auto")
        assert (changed.description, changed.features.state) == ("kitchen", "ready")
        assert [m.id for m in slloc.iter_maps(page_size=1)] == [demo_map.id]
        images = list(slloc.iter_images(demo_map.id, page_size=10))
        assert sorted(i.name for i in images) == sorted(m.with_suffix(".png").name for m in metas)

        params = json.loads((demo / "queries" / "query0000.params.json").read_text())
        result = slloc.localize(
            demo_map.id,
            demo / "queries" / "query0000.png",
            camera=params["camera"],
            params={"estimator": params["estimator"], "top_k": params["top_k"]},
        )
        assert isinstance(result, LocalizeResult)
        assert result.localized, result.reason
        assert result.cam_from_world is not None
        assert_near_truth(
            result.cam_from_world.rotation,
            result.cam_from_world.translation,
            ground_truth(demo, "query0000.png"),
        )

        # an image of that name is there already: 409, as a problem
        with pytest.raises(ProblemError) as taken:
            slloc.add_image_metadata(demo_map.id, metas[0].with_suffix(".png"), first)
        assert taken.value.status == 409
        # the map measures itself on three of its references, held out, with the server's
        # configuration
        started = slloc.start_evaluation(demo_map.id, configurations=[served], sample_size=3)
        seen: list[str] = []
        evaluation = slloc.wait_for_evaluation(
            demo_map.id,
            started.id,
            timeout_s=300.0,
            poll_s=0.2,
            on_progress=lambda e: seen.append(e.state),
        )
        assert evaluation.state == "done", evaluation.error
        assert seen[-1] == "done"
        assert evaluation.result is not None
        measured = evaluation.result.configurations[served]
        assert measured.held_out == 3 and measured.localized >= 2
        assert measured.references is not None and len(measured.references) == 3
        assert [e.id for e in slloc.list_evaluations(demo_map.id).items] == [started.id]

        slloc.delete_image(demo_map.id, added.id)
        assert slloc.get_map(demo_map.id).image_count == len(metas) - 1
        slloc.delete_map(demo_map.id)


def test_unknown_map_raises_the_problem(live_server: LocalServer) -> None:
    with Client(live_server.url) as slloc, pytest.raises(ProblemError) as raised:
        slloc.get_map("00000000-0000-4000-8000-000000000000")
    problem = raised.value
    assert problem.status == 404
    assert problem.type == "https://slloc.dev/problems/not-found"
    assert problem.title and problem.detail
    assert problem.request_id
    assert problem.response is not None
    assert problem.request_id == problem.response.headers["X-Request-ID"]


def test_invalid_input_carries_the_fields(live_server: LocalServer) -> None:
    with Client(live_server.url) as slloc, pytest.raises(ProblemError) as raised:
        slloc.create_map("")
    assert raised.value.status == 422
    assert raised.value.errors
    assert any("name" in json.dumps(error) for error in raised.value.errors)


class _Busy(BaseHTTPRequestHandler):
    """Answers 503 + ``Retry-After`` to the first ``busy`` requests, then an empty map page."""

    busy = 0
    retry_after = "1"
    seen = 0

    def do_GET(self) -> None:
        type(self).seen += 1
        if type(self).seen <= type(self).busy:
            body = json.dumps(
                {"type": "https://slloc.dev/problems/busy", "title": "Busy", "status": 503}
            ).encode()
            self.send_response(503)
            self.send_header("Content-Type", "application/problem+json")
            self.send_header("Retry-After", type(self).retry_after)
        else:
            body = json.dumps({"items": [], "total": 0, "offset": 0, "limit": 100}).encode()
            self.send_response(200)
            self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args: object) -> None:
        pass


@pytest.fixture
def busy_server() -> Iterator[tuple[str, type[_Busy]]]:
    handler = type("Busy", (_Busy,), {})
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", handler
    finally:
        server.shutdown()
        server.server_close()


def test_retry_after_is_honoured(busy_server: tuple[str, type[_Busy]]) -> None:
    url, handler = busy_server
    handler.busy = 2
    waits: list[float] = []
    with Client(url, max_retries=3, sleep=waits.append) as slloc:
        assert slloc.list_maps().total == 0
    assert waits == [1.0, 1.0]
    assert handler.seen == 3


def test_retries_are_bounded(busy_server: tuple[str, type[_Busy]]) -> None:
    url, handler = busy_server
    handler.busy = 10
    waits: list[float] = []
    with (
        Client(url, max_retries=2, sleep=waits.append) as slloc,
        pytest.raises(ProblemError) as raised,
    ):
        slloc.list_maps()
    assert waits == [1.0, 1.0]
    assert raised.value.status == 503 and raised.value.retry_after == 1.0
    assert raised.value.type == "https://slloc.dev/problems/busy"


def test_a_wait_past_the_limit_is_not_waited(busy_server: tuple[str, type[_Busy]]) -> None:
    url, handler = busy_server
    handler.busy, handler.retry_after = 1, "120"
    waits: list[float] = []
    with (
        Client(url, max_retry_wait_s=30, sleep=waits.append) as slloc,
        pytest.raises(ProblemError) as raised,
    ):
        slloc.list_maps()
    assert waits == [] and handler.seen == 1
    assert raised.value.retry_after == 120.0


def test_real_sleep_between_retries(busy_server: tuple[str, type[_Busy]]) -> None:
    """With the default sleep, the retry comes after Retry-After (1 s), not before."""
    url, handler = busy_server
    handler.busy = 1
    start = time.monotonic()
    with Client(url) as slloc:
        assert slloc.list_maps().total == 0
    assert time.monotonic() - start >= 0.95
