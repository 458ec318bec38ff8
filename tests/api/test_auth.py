"""API-key roles: admin manages maps and images, client localizes and reads."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from services.localization.localizer import Localizer
from tests.conftest import make_client

PROBLEM = "application/problem+json"
ADMIN = {"X-API-Key": "adm-secret"}
CLIENT = {"X-API-Key": "cli-secret"}


@pytest.fixture
def secured(database_url: str, localizer: Localizer) -> Iterator[TestClient]:
    with make_client(database_url, localizer, api_keys="adm-secret:admin,cli-secret:client") as c:
        yield c


def test_roles(secured: TestClient) -> None:
    assert secured.post("/v1/maps", json={"name": "m"}).status_code == 401
    assert (
        secured.post("/v1/maps", json={"name": "m"}, headers={"X-API-Key": "wrong"}).status_code
        == 401
    )
    forbidden = secured.post("/v1/maps", json={"name": "m"}, headers=CLIENT)
    assert forbidden.status_code == 403
    assert forbidden.headers["content-type"] == PROBLEM
    assert forbidden.json()["type"].endswith("/forbidden")

    created = secured.post("/v1/maps", json={"name": "m"}, headers=ADMIN)
    assert created.status_code == 201
    map_id = created.json()["id"]

    assert secured.get("/v1/maps").status_code == 401
    assert secured.get("/v1/maps", headers=CLIENT).status_code == 200
    assert secured.get(f"/v1/maps/{map_id}", headers=CLIENT).status_code == 200
    assert secured.get(f"/v1/maps/{map_id}/images", headers=CLIENT).status_code == 200
    assert secured.delete(f"/v1/maps/{map_id}", headers=CLIENT).status_code == 403
    assert (
        secured.post(
            f"/v1/maps/{map_id}/images",
            headers=CLIENT,
            files={"image": ("a.png", b"x", "image/png")},
            data={"metadata": "{}"},
        ).status_code
        == 403
    )
    # the client role may localize (a corrupt image: 422 proves it got past auth)
    localize = secured.post(
        f"/v1/maps/{map_id}/localize",
        headers=CLIENT,
        files={"image": ("q.png", b"not an image", "image/png")},
    )
    assert localize.status_code == 422
    assert (
        secured.post(
            f"/v1/maps/{map_id}/localize", files={"image": ("q.png", b"x", "image/png")}
        ).status_code
        == 401
    )
    assert secured.delete(f"/v1/maps/{map_id}", headers=ADMIN).status_code == 204


def test_health_needs_no_key(secured: TestClient) -> None:
    body = secured.get("/v1/health").json()
    assert body["status"] == "ok"
    assert {"auto", "e5p1"} <= set(body["models"]["estimators"])
    assert len(body["models"]["estimators"]) == 9


def test_bad_key_setting_is_refused() -> None:
    from app.settings import Settings

    with pytest.raises(ValueError, match="key:admin"):
        Settings(api_keys="justakey")
