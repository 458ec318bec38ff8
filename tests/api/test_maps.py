"""Maps: create, list, get, delete, against SQLite and PostgreSQL."""

from __future__ import annotations

import json

from fastapi.testclient import TestClient
from sqlalchemy import create_engine, func, select

from db.models import FeatureArray, ReferenceImage
from tests.conftest import create_map, image_metadata, upload_view
from tools.synthetic.scene import SyntheticView, encode_png

PROBLEM = "application/problem+json"


def test_create_list_get(client: TestClient) -> None:
    created = client.post("/v1/maps", json={"name": "kitchen", "description": "ground floor"})
    assert created.status_code == 201
    body = created.json()
    assert body["name"] == "kitchen" and body["description"] == "ground floor"
    assert body["image_count"] == 0
    create_map(client, "hall")

    listing = client.get("/v1/maps").json()
    assert listing["total"] == 2
    assert [m["name"] for m in listing["items"]] == ["kitchen", "hall"]
    assert (
        client.get("/v1/maps", params={"offset": 1, "limit": 1}).json()["items"][0]["name"]
        == "hall"
    )

    got = client.get(f"/v1/maps/{body['id']}")
    assert got.status_code == 200 and got.json() == body


def test_duplicate_name_is_409(client: TestClient) -> None:
    create_map(client, "same")
    response = client.post("/v1/maps", json={"name": "same"})
    assert response.status_code == 409
    assert response.headers["content-type"] == PROBLEM
    problem = response.json()
    assert problem["status"] == 409 and problem["type"].endswith("/conflict")
    assert client.get("/v1/maps").json()["total"] == 1


def test_unknown_map_is_404_problem(client: TestClient) -> None:
    for response in (client.get("/v1/maps/nope"), client.delete("/v1/maps/nope")):
        assert response.status_code == 404
        assert response.headers["content-type"] == PROBLEM
        assert response.json()["title"] == "Not found"
        assert response.json()["instance"] == "/v1/maps/nope"


def test_invalid_body_is_422_problem(client: TestClient) -> None:
    response = client.post("/v1/maps", json={"name": ""})
    assert response.status_code == 422
    assert response.headers["content-type"] == PROBLEM
    assert response.json()["errors"][0]["loc"][-1] == "name"


def test_delete_map_removes_images_and_features(
    client: TestClient, database_url: str, reference_views: list[SyntheticView]
) -> None:
    map_id = create_map(client)
    keep_id = create_map(client, "other")
    for view in reference_views[:2]:
        assert upload_view(client, map_id, view).status_code == 201
    assert upload_view(client, keep_id, reference_views[2]).status_code == 201
    assert client.get(f"/v1/maps/{map_id}").json()["image_count"] == 2

    assert client.delete(f"/v1/maps/{map_id}").status_code == 204
    assert client.get(f"/v1/maps/{map_id}").status_code == 404

    engine = create_engine(database_url)
    with engine.connect() as conn:
        images = conn.scalar(select(func.count()).select_from(ReferenceImage))
        arrays = conn.scalar(select(func.count()).select_from(FeatureArray))
        kept = conn.scalar(
            select(func.count())
            .select_from(FeatureArray)
            .where(FeatureArray.image_id.in_(select(ReferenceImage.id)))
        )
    engine.dispose()
    assert images == 1  # only the other map's image is left
    assert arrays == kept and arrays > 0


def test_feature_options_per_map(
    client: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    small = client.post(
        "/v1/maps", json={"name": "small", "features": {"max_keypoints": 300, "max_side": 320}}
    )
    assert small.status_code == 201
    features = small.json()["features"]
    assert (features["max_keypoints"], features["max_side"], features["state"]) == (
        300,
        320,
        "ready",
    )
    default_id = create_map(client, "default")
    features = client.get(f"/v1/maps/{default_id}").json()["features"]
    assert (features["max_keypoints"], features["max_side"]) == (None, None)
    small_id = small.json()["id"]
    counts = []
    for map_id in (small_id, default_id):
        response = upload_view(client, map_id, reference_views[0])
        assert response.status_code == 201  # type: ignore[attr-defined]
        counts.append(response.json()["num_keypoints"])  # type: ignore[attr-defined]
    assert counts[0] <= 300 < counts[1]
    for view in reference_views[1:8]:
        upload_view(client, small_id, view)
    query = query_views[0]
    result = client.post(
        f"/v1/maps/{small_id}/localize",
        files={"image": ("q.png", encode_png(query.image), "image/png")},
        data={"params": json.dumps({"camera": image_metadata(query)["camera"]})},
    ).json()
    # every retrieved reference was described with the map's options, so it is matchable
    assert result["retrieved"] and all(r["num_matches"] > 0 for r in result["retrieved"])


def test_bad_feature_options_are_422(client: TestClient) -> None:
    for features in ({"max_keypoints": 0}, {"max_side": 10}, {"max_keypoints": "many"}):
        response = client.post("/v1/maps", json={"name": "bad", "features": features})
        assert response.status_code == 422, features
        assert response.headers["content-type"] == PROBLEM
    assert client.get("/v1/maps").json()["total"] == 0
