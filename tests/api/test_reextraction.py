"""PATCH /v1/maps/{id}: new feature options describe the map's references anew from their
originals in the background while the map answers with the current descriptions, then it
switches at once; a restart resumes; the options it serves cancel; references without their
originals refuse the change. SQLite and PostgreSQL, real SIFT descriptions."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import update

from db.models import ReferenceImage
from db.repositories.reextraction import ReextractionRepository
from tests.conftest import create_map, localize_view, make_client, upload_view
from tests.polling import wait_until
from tools.synthetic.scene import SyntheticView

REFERENCES = 12
NEW_BUDGET = 300  # SIFT's default budget is 4096 keypoints


@pytest.fixture
def settings(tmp_path: Path) -> dict[str, object]:
    return {"data_dir": tmp_path / "data", "features": "sift"}


@pytest.fixture
def client(database_url: str, localizer: Any, settings: dict[str, object]) -> Iterator[TestClient]:
    with make_client(database_url, localizer, **settings) as c:
        yield c


def _map_with_references(client: TestClient, views: list[SyntheticView]) -> str:
    map_id = create_map(client)
    for view in views[:REFERENCES]:
        assert upload_view(client, map_id, view).status_code == 201
    return map_id


def _localize(client: TestClient, map_id: str, view: SyntheticView) -> dict[str, Any]:
    response = localize_view(client, map_id, view)
    assert response.status_code == 200, response.text
    answer: dict[str, Any] = response.json()
    return answer


def _hold_worker(client: TestClient) -> threading.Event:
    """Occupies the re-extraction worker's one thread until the event is set, so that a
    map's job waits behind it."""
    release = threading.Event()
    client.app.state.reextractor.worker.schedule("hold", release.wait)  # type: ignore[attr-defined]
    return release


def _ready(client: TestClient, map_id: str) -> dict[str, Any]:
    """The map once its re-description has switched."""

    def body() -> dict[str, Any]:
        answer: dict[str, Any] = client.get(f"/v1/maps/{map_id}").json()
        return answer

    assert wait_until(lambda: body()["features"]["state"] == "ready", timeout_s=120.0)
    return body()


def test_new_options_switch_after_every_reference_is_described(
    client: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    map_id = _map_with_references(client, reference_views)
    before = client.get(f"/v1/maps/{map_id}").json()
    [old_model] = [g["feature_model"] for g in before["feature_models"]["described_by"]]
    release = _hold_worker(client)
    try:
        patched = client.patch(f"/v1/maps/{map_id}", json={"features": {"max_keypoints": 300}})
        assert patched.status_code == 200, patched.text
        features = patched.json()["features"]
        assert features["state"] == "re-extracting"
        assert features["max_keypoints"] is None  # still serving the old options
        assert features["pending"] == {
            "preset": "sift",
            "max_keypoints": NEW_BUDGET,
            "max_side": None,
        }
        assert features["progress"] == {"described": 0, "total": REFERENCES}
        assert features["preset"] == "sift"
        # the map keeps answering with its current descriptions meanwhile
        answer = _localize(client, map_id, query_views[0])
        assert answer["localized"], answer
    finally:
        release.set()
    after = _ready(client, map_id)
    assert after["features"]["max_keypoints"] == NEW_BUDGET
    assert after["features"]["pending"] is None and after["features"]["progress"] is None
    [group] = after["feature_models"]["described_by"]
    assert group["feature_model"] != old_model and group["image_count"] == REFERENCES
    assert after["feature_models"]["servable"]
    images = client.get(f"/v1/maps/{map_id}/images").json()["items"]
    assert all(0 < image["num_keypoints"] <= NEW_BUDGET for image in images)
    answer = _localize(client, map_id, query_views[0])
    assert answer["localized"], answer
    metrics = client.get("/metrics").text
    assert f"slloc_references_described_again_total {float(REFERENCES)}" in metrics


def test_a_restart_resumes_the_redescription(
    database_url: str,
    localizer: Any,
    settings: dict[str, object],
    reference_views: list[SyntheticView],
) -> None:
    with make_client(database_url, localizer, **settings) as first:
        map_id = _map_with_references(first, reference_views)
        sessions = first.app.state.sessions  # type: ignore[attr-defined]
    # what a PATCH leaves when the server stops before its job ran
    with sessions.begin() as session:
        ReextractionRepository(session).start(map_id, None, NEW_BUDGET, None)
    with make_client(database_url, localizer, **settings) as second:
        after = _ready(second, map_id)
        assert after["features"]["max_keypoints"] == NEW_BUDGET


def test_the_served_options_cancel_and_other_fields_change(
    client: TestClient, reference_views: list[SyntheticView]
) -> None:
    map_id = _map_with_references(client, reference_views)
    release = _hold_worker(client)
    try:
        client.patch(f"/v1/maps/{map_id}", json={"features": {"max_keypoints": NEW_BUDGET}})
        cancelled = client.patch(
            f"/v1/maps/{map_id}",
            json={
                "features": {"max_keypoints": None, "max_side": None},
                "description": "kitchen",
                "default_estimator": "e5p1",
            },
        )
        assert cancelled.status_code == 200, cancelled.text
        body = cancelled.json()
        assert body["features"]["state"] == "ready" and body["features"]["pending"] is None
        assert (body["description"], body["default_estimator"]) == ("kitchen", "e5p1")
    finally:
        release.set()
    client.app.state.reextractor.worker.wait(60)  # type: ignore[attr-defined]
    assert client.get(f"/v1/maps/{map_id}").json()["features"]["max_keypoints"] is None


def test_refusals(client: TestClient, reference_views: list[SyntheticView]) -> None:
    empty = create_map(client, "empty")
    changed = client.patch(f"/v1/maps/{empty}", json={"features": {"max_side": 512}})
    assert changed.status_code == 200  # no references: at once
    assert changed.json()["features"] == {
        "max_keypoints": None,
        "max_side": 512,
        "preset": "sift",
        "auto": True,
        "state": "ready",
        "pending": None,
        "progress": None,
    }
    too_many = client.patch(f"/v1/maps/{empty}", json={"features": {"max_keypoints": 10**4}})
    assert too_many.status_code == 422
    other = client.patch(f"/v1/maps/{empty}", json={"features": {"preset": "aliked"}})
    assert other.status_code == 422 and "aliked is not served here" in other.text
    same = client.patch(f"/v1/maps/{empty}", json={"features": {"preset": "sift"}})
    assert same.status_code == 200
    assert client.patch("/v1/maps/nope", json={"description": "x"}).status_code == 404
    map_id = _map_with_references(client, reference_views[:2])
    sessions = client.app.state.sessions  # type: ignore[attr-defined]
    with sessions.begin() as session:  # as if added before originals were kept
        session.execute(
            update(ReferenceImage).where(ReferenceImage.map_id == map_id).values(original_key=None)
        )
    refused = client.patch(f"/v1/maps/{map_id}", json={"features": {"max_keypoints": 300}})
    assert refused.status_code == 409
    assert "before originals were kept" in refused.json()["detail"]
    assert client.get(f"/v1/maps/{map_id}").json()["features"]["state"] == "ready"


def test_references_of_another_extractor_are_described_with_the_servers(
    client: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    """After the server's SLLOC_FEATURES changed, the map's own options re-describe what
    the previous extractor described."""
    map_id = _map_with_references(client, reference_views)
    sessions = client.app.state.sessions  # type: ignore[attr-defined]
    with sessions.begin() as session:
        session.execute(
            update(ReferenceImage)
            .where(ReferenceImage.map_id == map_id)
            .values(feature_model="aliked-n16-1024-640")
        )
    assert not client.get(f"/v1/maps/{map_id}").json()["feature_models"]["servable"]
    patched = client.patch(f"/v1/maps/{map_id}", json={"features": {}})
    assert patched.status_code == 200, patched.text
    after = _ready(client, map_id)
    assert after["feature_models"]["servable"] and after["features"]["max_keypoints"] is None
    assert _localize(client, map_id, query_views[0])["localized"]
