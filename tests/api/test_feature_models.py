"""A server that lacks the models a map's stored features need says so (issue "maps keep their
images", 4): the map names what its references were described by and whether this server can
serve them, /v1/health lists the maps it cannot serve, and a localize is a 409
feature-models-missing problem naming the missing models, never ``no_references``.

The references are described by the shared SIFT localizer, then their rows relabelled as an
ALIKED server stores them (``aliked-n16-1024-640``); the server has only the XFeat models
built (manifest entries in a temporary models folder), as in the issue's report."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import update

from db.models import ReferenceImage
from tests.conftest import create_map, make_client, upload_view, write_model_files
from tools.synthetic.scene import SyntheticView, encode_png

ALIKED = "aliked-n16-1024-640"


@pytest.fixture
def xfeat_only_client(database_url: str, localizer: Any, tmp_path: Path) -> Iterator[TestClient]:
    models = tmp_path / "models"
    models.mkdir()
    write_model_files(models, "xfeat-lg")
    with make_client(database_url, localizer, models_dir=models, data_dir=tmp_path) as client:
        yield client


def _relabel(client: TestClient, map_id: str, feature_model: str) -> None:
    sessions = client.app.state.sessions  # type: ignore[attr-defined]
    with sessions.begin() as session:
        session.execute(
            update(ReferenceImage)
            .where(ReferenceImage.map_id == map_id)
            .values(feature_model=feature_model)
        )


def _localize(client: TestClient, map_id: str, view: SyntheticView) -> object:
    return client.post(
        f"/v1/maps/{map_id}/localize",
        files={"image": ("q.png", encode_png(view.image), "image/png")},
    )


def test_a_map_of_missing_models_is_named_everywhere(
    xfeat_only_client: TestClient,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    client = xfeat_only_client
    served = create_map(client, "served")
    aliked = create_map(client, "aliked")
    empty = create_map(client, "empty")
    for view in reference_views[:12]:
        assert upload_view(client, aliked, view).status_code == 201  # type: ignore[attr-defined]
    for view in reference_views[:4]:
        assert upload_view(client, served, view).status_code == 201  # type: ignore[attr-defined]
    server_model = client.get(f"/v1/maps/{served}").json()["feature_models"]
    assert server_model["servable"] is True and server_model["detail"] is None
    _relabel(client, aliked, ALIKED)

    body = client.get(f"/v1/maps/{aliked}").json()
    assert body["image_count"] == 12
    models = body["feature_models"]
    assert models["servable"] is False
    assert models["server_feature_model"] == server_model["server_feature_model"]
    assert [
        (g["feature_model"], g["image_count"], g["served"]) for g in models["described_by"]
    ] == [(ALIKED, 12, False)]
    assert models["unserved_image_count"] == 12
    assert models["missing_models"] == ["aliked-n16", "lightglue-aliked"]
    assert "aliked" in models["configurations"]
    assert "aliked-n16" in models["detail"] and "slloc models build" in models["detail"]

    response = _localize(client, aliked, query_views[0])
    assert response.status_code == 409  # type: ignore[attr-defined]
    problem = response.json()  # type: ignore[attr-defined]
    assert response.headers["content-type"] == "application/problem+json"  # type: ignore[attr-defined]
    assert problem["type"].endswith("/feature-models-missing")
    assert problem["title"] == "Feature models missing"
    assert "aliked-n16" in problem["detail"] and "lightglue-aliked" in problem["detail"]
    assert ALIKED in problem["detail"]

    # the served map and the empty map answer as before
    assert _localize(client, served, query_views[0]).status_code == 200  # type: ignore[attr-defined]
    empty_answer = _localize(client, empty, query_views[0])
    assert empty_answer.json()["reason"] == "no_references"  # type: ignore[attr-defined]
    assert client.get(f"/v1/maps/{empty}").json()["feature_models"]["servable"] is True

    health = client.get("/v1/health").json()
    assert health["status"] == "degraded"
    assert health["unservable_map_count"] == 1
    [listed] = health["unservable_maps"]
    assert (listed["id"], listed["name"], listed["image_count"]) == (aliked, "aliked", 12)
    assert listed["described_by"] == [ALIKED]
    assert listed["missing_models"] == ["aliked-n16", "lightglue-aliked"]
    page = client.get("/v1/maps").json()["items"]
    assert {m["name"]: m["feature_models"]["servable"] for m in page} == {
        "served": True,
        "aliked": False,
        "empty": True,
    }


def test_a_partly_served_map_localizes_and_names_the_rest(
    xfeat_only_client: TestClient,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    client = xfeat_only_client
    map_id = create_map(client)
    for view in reference_views[:6]:
        assert upload_view(client, map_id, view).status_code == 201  # type: ignore[attr-defined]
    sessions = client.app.state.sessions  # type: ignore[attr-defined]
    with sessions.begin() as session:
        first = session.scalars(
            ReferenceImage.__table__.select().with_only_columns(ReferenceImage.id).limit(2)
        ).all()
        session.execute(
            update(ReferenceImage).where(ReferenceImage.id.in_(first)).values(feature_model=ALIKED)
        )
    models = client.get(f"/v1/maps/{map_id}").json()["feature_models"]
    assert models["servable"] is True
    assert models["unserved_image_count"] == 2
    assert models["missing_models"] == ["aliked-n16", "lightglue-aliked"]
    assert _localize(client, map_id, query_views[0]).status_code == 200  # type: ignore[attr-defined]
    health = client.get("/v1/health").json()
    assert (health["status"], health["unservable_map_count"]) == ("ok", 0)


def test_built_models_under_another_configuration(
    database_url: str,
    localizer: Any,
    tmp_path: Path,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    """The map's models are built but the server runs another configuration: no model is
    missing, the answer names the configurations to run."""
    models = tmp_path / "models"
    models.mkdir()
    write_model_files(models, "xfeat-lg", "aliked")
    with make_client(database_url, localizer, models_dir=models, data_dir=tmp_path) as client:
        map_id = create_map(client)
        for view in reference_views[:3]:
            assert upload_view(client, map_id, view).status_code == 201  # type: ignore[attr-defined]
        _relabel(client, map_id, ALIKED)
        response = _localize(client, map_id, query_views[0])
        assert response.status_code == 409  # type: ignore[attr-defined]
        detail = response.json()["detail"]  # type: ignore[attr-defined]
        assert "SLLOC_FEATURES" in detail and "aliked" in detail
        assert client.get(f"/v1/maps/{map_id}").json()["feature_models"]["missing_models"] == []
