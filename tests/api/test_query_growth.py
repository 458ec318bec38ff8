"""Maps that grow from their queries: a confidently localized query with its intrinsics is
added as a reference where it adds a view, once per place and direction, and only on maps
that ask for it. SQLite and PostgreSQL, real SIFT on rendered views."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from services.capture.spacing import map_spacing, new_views
from tests.conftest import localize_view, make_client, upload_view
from tools.synthetic.scene import SyntheticView

MAPPED = 12


@pytest.fixture
def client(database_url: str, localizer: Any, tmp_path: Path) -> Any:
    with make_client(database_url, localizer, data_dir=tmp_path / "data") as c:
        yield c


def _map(client: TestClient, views: list[SyntheticView], **body: object) -> str:
    created = client.post("/v1/maps", json={"name": "scene", **body})
    assert created.status_code == 201, created.text
    map_id = str(created.json()["id"])
    for view in views:
        assert upload_view(client, map_id, view).status_code == 201
    return map_id


def _adds_a_view(references: list[SyntheticView], query: SyntheticView) -> bool:
    """Whether the references lack the query's view (none within their spacing looking
    within 15° of it)."""
    poses = [v.cam_from_world for v in references]
    spacing = map_spacing(np.array([p.center for p in poses]))
    assert spacing is not None
    return bool(new_views([query.cam_from_world], poses, spacing))


def _queries_added(client: TestClient, map_id: str) -> list[str]:
    client.app.state.query_growth.worker.wait(60.0)  # type: ignore[attr-defined]
    items = client.get(f"/v1/maps/{map_id}/images", params={"limit": 1000}).json()["items"]
    return [item["name"] for item in items if item["name"].startswith("query/")]


def test_a_map_grows_from_its_confident_queries_once_per_view(
    client: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    mapped = reference_views[:MAPPED]
    map_id = _map(client, mapped, grow_from_queries=True)
    assert client.get(f"/v1/maps/{map_id}").json()["grow_from_queries"] is True
    new = [q for q in query_views if _adds_a_view(mapped, q)]
    known = [q for q in query_views if not _adds_a_view(mapped, q)]
    assert new and known, "the views must include both kinds"
    # a query whose view the map has is not added
    assert localize_view(client, map_id, known[0]).json()["localized"]
    assert _queries_added(client, map_id) == []
    answer = localize_view(client, map_id, new[0]).json()
    assert answer["localized"] and answer["confidence"] >= 0.95, answer
    [added] = _queries_added(client, map_id)
    image = client.get(f"/v1/maps/{map_id}/images", params={"limit": 1000}).json()["items"][-1]
    assert image["name"] == added and image["has_original"]
    # the same view again adds nothing: the map has it now
    assert localize_view(client, map_id, new[0]).json()["localized"]
    assert _queries_added(client, map_id) == [added]
    assert "slloc_queries_added_total 1.0" in client.get("/metrics").text


def test_only_maps_that_ask_grow(
    client: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    mapped = reference_views[:MAPPED]
    map_id = _map(client, mapped)
    assert client.get(f"/v1/maps/{map_id}").json()["grow_from_queries"] is False
    query = next(q for q in query_views if _adds_a_view(mapped, q))
    assert localize_view(client, map_id, query).json()["localized"]
    assert _queries_added(client, map_id) == []
    patched = client.patch(f"/v1/maps/{map_id}", json={"grow_from_queries": True})
    assert patched.status_code == 200 and patched.json()["grow_from_queries"] is True
    assert localize_view(client, map_id, query).json()["localized"]
    assert len(_queries_added(client, map_id)) == 1
    refused = client.patch(f"/v1/maps/{map_id}", json={"grow_from_queries": "yes"})
    assert refused.status_code == 422
