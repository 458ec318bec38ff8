"""POST /v1/maps/{id}/evaluations: a map measures itself on its own references, each held out
and localized against the rest from its original, in the background; the result reads back
through the API and /metrics. SQLite and PostgreSQL, real SIFT descriptions of rendered views
with exact poses."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from tests.conftest import create_map, localize_view, make_client, seen_elsewhere, upload_view
from tests.polling import wait_until
from tools.synthetic.scene import SyntheticView

REFERENCES = 12
HELD_OUT = 6


@pytest.fixture
def client(database_url: str, localizer: Any, tmp_path: Path) -> Iterator[TestClient]:
    # no exported model: only sift can run
    settings = {"data_dir": tmp_path / "data", "features": "sift", "models_dir": tmp_path / "none"}
    with make_client(database_url, localizer, **settings) as c:
        yield c


def _map(client: TestClient, views: list[SyntheticView], count: int = REFERENCES) -> str:
    map_id = create_map(client)
    for view in views[:count]:
        assert upload_view(client, map_id, view).status_code == 201
    return map_id


def _hold_worker(client: TestClient) -> threading.Event:
    """Occupies the evaluation worker's one thread until the event is set."""
    release = threading.Event()
    client.app.state.evaluator.worker.schedule("hold", release.wait)  # type: ignore[attr-defined]
    return release


def _finished(client: TestClient, location: str) -> dict[str, Any]:
    def body() -> dict[str, Any]:
        answer: dict[str, Any] = client.get(location).json()
        return answer

    assert wait_until(lambda: body()["state"] not in ("queued", "running"), timeout_s=180.0)
    return body()


def test_a_map_measures_itself(client: TestClient, reference_views: list[SyntheticView]) -> None:
    map_id = _map(client, reference_views)
    started = client.post(
        f"/v1/maps/{map_id}/evaluations",
        json={"configurations": ["sift"], "sample_size": HELD_OUT},
    )
    assert started.status_code == 202, started.text
    location = started.headers["Location"]
    assert started.json()["state"] == "queued"
    assert started.json()["request"]["configurations"] == ["sift"]
    evaluation = _finished(client, location)
    assert evaluation["state"] == "done", evaluation
    assert evaluation["progress"] == {"done": HELD_OUT, "total": HELD_OUT}
    result = evaluation["result"]
    assert result["recommended"] == "sift" and result["served"] == "sift"
    assert result["references"] == REFERENCES
    sift = result["configurations"]["sift"]
    assert sift["held_out"] == HELD_OUT
    # exact poses and a rendered scene: each held-out reference is found within millimetres
    assert sift["localized"] == HELD_OUT and sift["recall"]["5cm_5deg"] == 1.0
    assert sift["position_error_m"]["p90"] < 0.01
    assert sift["confidence"]["precision"] in (None, 1.0)
    assert sift["latency_ms"]["median"] > 0 and sift["duration_s"] > 0
    names = {view.name for view in reference_views[:REFERENCES]}
    held = sift["references"]
    assert len(held) == HELD_OUT and {r["name"] for r in held} <= names
    assert len({r["image_id"] for r in held}) == HELD_OUT  # spread: no reference twice
    assert all(r["localized"] and r["position_error_m"] < 0.01 for r in held)
    # each was localized against the others: the nearest of them lies a view's spacing away
    assert all(0 < r["nearest_reference_m"] < 10 for r in held)
    distances = sorted(r["nearest_reference_m"] for r in held)
    assert sift["nearest_reference_m"]["median"] == distances[(HELD_OUT + 1) // 2 - 1]
    listed = client.get(f"/v1/maps/{map_id}/evaluations").json()
    assert listed["total"] == 1
    [item] = listed["items"]
    assert item["id"] == evaluation["id"]
    assert item["result"]["configurations"]["sift"]["references"] is None
    # the map's coverage reads it: every held-out reference in its cell, none failed
    coverage = client.get(f"/v1/maps/{map_id}/coverage").json()
    assert coverage["evaluation_id"] == evaluation["id"]
    assert sum(c["references"] for c in coverage["cells"]) == REFERENCES
    assert sum(c["held_out"] for c in coverage["cells"]) == HELD_OUT
    assert all(c["failed"] == 0 for c in coverage["cells"])
    assert all(c["why"] in ([], ["a single reference"]) for c in coverage["cells"])
    assert coverage["weak"] == sum(c["weak"] for c in coverage["cells"])
    plane = coverage["plane"]
    assert abs(float(np.dot(plane["u"], plane["v"]))) < 1e-9
    tiny = client.get(f"/v1/maps/{map_id}/coverage", params={"cell_m": 1e-6})
    assert tiny.status_code == 422 and "more than 20000 cells" in tiny.json()["detail"]
    metrics = client.get("/metrics").text
    assert 'slloc_self_evaluations_total{state="done"} 1.0' in metrics
    assert f"slloc_self_evaluation_queries_total {float(HELD_OUT)}" in metrics
    assert (
        f'slloc_map_self_evaluation_recall{{configuration="sift",map="scene",map_id="{map_id}",'
        'threshold="5cm_5deg"} 1.0' in metrics
    )


def test_neighbours_within_the_radius_are_held_out_too(
    client: TestClient, reference_views: list[SyntheticView]
) -> None:
    """A radius that covers the whole map leaves each held-out query nothing to match."""
    map_id = _map(client, reference_views, 6)
    started = client.post(
        f"/v1/maps/{map_id}/evaluations",
        json={"configurations": ["sift"], "sample_size": 3, "holdout_radius_m": 1000},
    )
    assert started.status_code == 202, started.text
    evaluation = _finished(client, started.headers["Location"])
    sift = evaluation["result"]["configurations"]["sift"]
    assert sift["localized"] == 0 and sift["failures"] == {"no_references": 3}
    assert sift["recall"]["25cm_2deg"] == 0.0 and sift["position_error_m"]["median"] is None
    assert sift["nearest_reference_m"]["median"] is None
    assert all(r["nearest_reference_m"] is None for r in sift["references"])
    assert evaluation["result"]["recommended"] is None


def test_refusals(client: TestClient, reference_views: list[SyntheticView]) -> None:
    map_id = _map(client, reference_views, 1)
    url = f"/v1/maps/{map_id}/evaluations"
    one = client.post(url, json={"configurations": ["sift"]})
    assert one.status_code == 409 and "two references" in one.json()["detail"]
    assert upload_view(client, map_id, reference_views[1]).status_code == 201
    unknown = client.post(url, json={"configurations": ["nope"]})
    assert unknown.status_code == 422 and "nope" in unknown.json()["detail"]
    # a configuration other than the server's needs SLLOC_EVALUATION_FEATURES
    other = client.post(url, json={"configurations": ["xfeat-lg"]})
    assert other.status_code == 422
    assert "xfeat-lg is not measured on this server" in other.json()["detail"]
    for body in ({"sample_size": 0}, {"top_k": 51}, {"holdout_radius_m": -1}, {"estimator": "x"}):
        assert client.post(url, json=body).status_code == 422, body
    assert client.post("/v1/maps/unknown/evaluations", json={}).status_code == 404
    assert client.get(f"{url}/unknown").status_code == 404
    release = _hold_worker(client)
    try:
        first = client.post(url, json={"configurations": ["sift"]})
        assert first.status_code == 202, first.text
        second = client.post(url, json={"configurations": ["sift"]})
        assert second.status_code == 409 and first.json()["id"] in second.json()["detail"]
        # cancelled before it ran: it ends cancelled and runs no query
        assert client.delete(first.headers["Location"]).status_code == 204
    finally:
        release.set()
    client.app.state.evaluator.worker.wait(60.0)  # type: ignore[attr-defined]
    cancelled = client.get(first.headers["Location"]).json()
    assert cancelled["state"] == "cancelled" and cancelled["result"] is None
    # a finished evaluation is deleted
    assert client.delete(first.headers["Location"]).status_code == 204
    assert client.get(first.headers["Location"]).status_code == 404


def test_an_interrupted_evaluation_runs_again_after_a_restart(
    database_url: str, localizer: Any, tmp_path: Path, reference_views: list[SyntheticView]
) -> None:
    settings = {"data_dir": tmp_path / "data", "features": "sift", "models_dir": tmp_path / "none"}
    with make_client(database_url, localizer, **settings) as client:
        map_id = _map(client, reference_views, 6)
        release = _hold_worker(client)
        started = client.post(
            f"/v1/maps/{map_id}/evaluations", json={"configurations": ["sift"], "sample_size": 2}
        )
        assert started.status_code == 202
        client.app.state.evaluator._stopping.set()  # type: ignore[attr-defined]
        release.set()
    with make_client(database_url, localizer, **settings) as client:
        evaluation = _finished(client, started.headers["Location"])
        assert evaluation["state"] == "done", evaluation
        assert evaluation["result"]["configurations"]["sift"]["localized"] == 2


def test_a_map_that_shrank_before_its_turn_fails_with_the_reason(
    client: TestClient, reference_views: list[SyntheticView]
) -> None:
    map_id = _map(client, reference_views, 2)
    release = _hold_worker(client)
    try:
        started = client.post(f"/v1/maps/{map_id}/evaluations", json={"configurations": ["sift"]})
        assert started.status_code == 202, started.text
        [image, _] = client.get(f"/v1/maps/{map_id}/images").json()["items"]
        assert client.delete(f"/v1/maps/{map_id}/images/{image['id']}").status_code == 204
    finally:
        release.set()
    evaluation = _finished(client, started.headers["Location"])
    assert evaluation["state"] == "failed" and evaluation["result"] is None
    assert "fewer than two usable references" in evaluation["error"]
    assert 'slloc_self_evaluations_total{state="failed"} 1.0' in client.get("/metrics").text


def test_other_configurations_are_measured_where_the_settings_allow_them(
    database_url: str, localizer: Any, tmp_path: Path, reference_views: list[SyntheticView]
) -> None:
    """SLLOC_EVALUATION_FEATURES lists them: measured by default when their models are built,
    refused by name when they are not."""
    models = tmp_path / "none"
    settings = {"data_dir": tmp_path / "data", "features": "sift", "models_dir": models}
    with make_client(database_url, localizer, evaluation_features="xfeat-lg", **settings) as c:
        map_id = _map(c, reference_views, 2)
        missing = c.post(f"/v1/maps/{map_id}/evaluations", json={"configurations": ["xfeat-lg"]})
        assert missing.status_code == 422
        assert "xfeat-lg cannot run on this server" in missing.json()["detail"]
        # by default, the server's own and those allowed whose models are built (none here)
        started = c.post(f"/v1/maps/{map_id}/evaluations", json={"sample_size": 1})
        assert started.status_code == 202, started.text
        assert started.json()["request"]["configurations"] == ["sift"]
    with pytest.raises(ValueError, match="evaluation_features: unknown nope"):
        make_client(database_url, localizer, evaluation_features="sift,nope", **settings)


def test_a_reference_whose_image_shows_another_place_is_flagged_by_the_next_evaluation(
    client: TestClient, reference_views: list[SyntheticView]
) -> None:
    views = reference_views[:REFERENCES]
    swapped = views[5]
    map_id = _map(client, [v for v in views if v is not swapped])
    assert upload_view(client, map_id, seen_elsewhere(swapped)).status_code == 201

    def evaluate() -> dict[str, Any]:
        started = client.post(
            f"/v1/maps/{map_id}/evaluations",
            json={"configurations": ["sift"], "sample_size": REFERENCES},
        )
        assert started.status_code == 202, started.text
        evaluation = _finished(client, started.headers["Location"])
        assert evaluation["state"] == "done", evaluation
        return evaluation

    evaluation = evaluate()
    # held out itself it localizes nowhere near where it is stored; its neighbours, held out,
    # localize and no longer match it
    held = {r["name"]: r for r in evaluation["result"]["configurations"]["sift"]["references"]}
    assert not held[swapped.name]["localized"] or held[swapped.name]["position_error_m"] > 0.25
    [stale] = evaluation["result"]["stale"]
    assert stale["name"] == swapped.name and stale["retired"] is False
    assert f"self-evaluation {evaluation['id']}" in stale["reason"]
    flagged = client.get(f"/v1/maps/{map_id}/images", params={"stale": True}).json()
    assert [item["name"] for item in flagged["items"]] == [swapped.name]
    fresh = client.get(f"/v1/maps/{map_id}/images", params={"stale": False}).json()
    assert fresh["total"] == REFERENCES - 1
    # a map that retires its stale references deletes them at the next evaluation
    patched = client.patch(f"/v1/maps/{map_id}", json={"retire_stale": True})
    assert patched.status_code == 200
    [retired] = evaluate()["result"]["stale"]
    assert retired["name"] == swapped.name and retired["retired"] is True
    names = [item["name"] for item in client.get(f"/v1/maps/{map_id}/images").json()["items"]]
    assert swapped.name not in names and len(names) == REFERENCES - 1


def test_where_queries_fail_the_map_is_weak(
    client: TestClient,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    map_id = _map(client, reference_views)
    localized = 0
    for view in query_views[:4]:
        answer = localize_view(client, map_id, view)
        assert answer.status_code == 200, answer.text
        localized += bool(answer.json()["localized"])
    # another room, seen from the map's poses: retrieved against the map, never localized
    for view in reference_views[:6]:
        answer = localize_view(client, map_id, seen_elsewhere(view))
        assert answer.status_code == 200 and not answer.json()["localized"], answer.text
    client.app.state.query_outcomes.flush()  # type: ignore[attr-defined]
    coverage = client.get(f"/v1/maps/{map_id}/coverage", params={"cell_m": 100.0}).json()
    [cell] = coverage["cells"]  # one cell holds the whole map
    assert (cell["queries_localized"], cell["queries_failed"]) == (localized, 6)
    assert localized >= 3
    assert "6 of " in " ".join(cell["why"]) and cell["weak"] is True
    # counted once: a second flush writes nothing more
    client.app.state.query_outcomes.flush()  # type: ignore[attr-defined]
    again = client.get(f"/v1/maps/{map_id}/coverage", params={"cell_m": 100.0}).json()
    assert again["cells"][0]["queries_failed"] == 6
