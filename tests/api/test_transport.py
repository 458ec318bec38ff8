"""HTTP hygiene: 413 for every oversize path, Allow on 405, Connection: close after a 500,
auth before the body is read, health never waiting behind other requests (issue #14)."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator

import anyio
import pytest
from fastapi.testclient import TestClient

from app.api.deps import get_localizers
from services.components import Localizers
from services.localization.localizer import Localizer
from tests.conftest import create_map, make_client

PROBLEM = "application/problem+json"
MULTIPART = "multipart/form-data; boundary=slloc-boundary"


def _chunks(total: int, size: int = 64 * 1024) -> Iterator[bytes]:
    """``total`` bytes as a generator, which the test client sends chunked (no length)."""
    sent = 0
    while sent < total:
        yield b"x" * min(size, total - sent)
        sent += size


def _assert_too_large(response: object) -> None:
    assert response.status_code == 413, response.text  # type: ignore[attr-defined]
    assert response.headers["content-type"] == PROBLEM  # type: ignore[attr-defined]
    assert response.json()["type"].endswith("/payload-too-large")  # type: ignore[attr-defined]


@pytest.fixture
def small_uploads(database_url: str, localizer: Localizer) -> Iterator[TestClient]:
    """Body limit 2 × 1000 bytes + 1 MiB."""
    with make_client(database_url, localizer, max_upload_bytes=1000) as c:
        yield c


def test_chunked_body_over_the_limit_is_413(small_uploads: TestClient) -> None:
    map_id = create_map(small_uploads)
    too_much = 2 * 1000 + 1024 * 1024 + 1
    upload = small_uploads.post(
        f"/v1/maps/{map_id}/images",
        content=_chunks(too_much),
        headers={"content-type": MULTIPART},
    )
    _assert_too_large(upload)
    assert upload.headers["connection"] == "close"
    as_json = small_uploads.post(
        "/v1/maps", content=_chunks(too_much), headers={"content-type": "application/json"}
    )
    _assert_too_large(as_json)
    assert small_uploads.get(f"/v1/maps/{map_id}").json()["image_count"] == 0


def test_metadata_part_over_1_mib_is_413(client: TestClient) -> None:
    map_id = create_map(client)
    response = client.post(
        f"/v1/maps/{map_id}/images",
        files={"image": ("a.png", b"x", "image/png")},
        data={"metadata": json.dumps({"name": "n" * (1024 * 1024)})},
    )
    _assert_too_large(response)
    params = client.post(
        f"/v1/maps/{map_id}/localize",
        files={"image": ("q.png", b"x", "image/png")},
        data={"params": " " * (1024 * 1024 + 1)},
    )
    _assert_too_large(params)


def test_405_names_the_allowed_methods(client: TestClient) -> None:
    response = client.put("/v1/maps")
    assert response.status_code == 405
    assert response.headers["content-type"] == PROBLEM
    assert response.headers["allow"] == "GET, POST"


def test_500_says_connection_close(database_url: str, localizer: Localizer) -> None:
    def broken() -> Localizers:
        raise RuntimeError("boom")

    with make_client(database_url, localizer, raise_server_exceptions=False) as c:
        c.app.dependency_overrides[get_localizers] = broken  # type: ignore[attr-defined]
        response = c.get("/v1/health")
    assert response.status_code == 500
    assert response.headers["content-type"] == PROBLEM
    assert response.headers["connection"] == "close"


@pytest.fixture
def secured(database_url: str, localizer: Localizer) -> Iterator[TestClient]:
    with make_client(database_url, localizer, api_keys="adm-secret:admin,cli-secret:client") as c:
        yield c


def test_auth_is_checked_before_the_body(secured: TestClient) -> None:
    malformed = {"content-type": "application/json"}
    response = secured.post("/v1/maps", content=b'{"name": ', headers=malformed)
    assert response.status_code == 401
    assert response.headers["content-type"] == PROBLEM
    assert response.headers["www-authenticate"] == "X-API-Key"
    assert (
        secured.post(
            "/v1/maps", content=b'{"name": ', headers={**malformed, "X-API-Key": "wrong"}
        ).status_code
        == 401
    )
    wrong_role = secured.post(
        "/v1/maps", content=b'{"name": ', headers={**malformed, "X-API-Key": "cli-secret"}
    )
    assert wrong_role.status_code == 403
    # a valid key still gets the body's own problem
    admin = {**malformed, "X-API-Key": "adm-secret"}
    assert secured.post("/v1/maps", content=b'{"name": ', headers=admin).status_code == 422
    garbage_form = secured.post(
        "/v1/maps/any/localize", content=b"--x\r\n", headers={"content-type": MULTIPART}
    )
    assert garbage_form.status_code == 401
    assert secured.get("/v1/maps", headers={"X-API-Key": "adm-secret"}).json()["total"] == 0


def test_health_does_not_wait_for_the_thread_pool(client: TestClient) -> None:
    """Every thread-pool token taken (as by that many blocked requests): health answers."""
    portal = client.portal
    assert portal is not None
    limiter = portal.call(anyio.to_thread.current_default_thread_limiter)
    holders = [object() for _ in range(int(limiter.total_tokens))]
    for holder in holders:
        portal.call(limiter.acquire_on_behalf_of, holder)
    answers: list[int] = []
    request = threading.Thread(
        target=lambda: answers.append(client.get("/v1/health").status_code), daemon=True
    )
    try:
        request.start()
        request.join(timeout=20)  # a bound on a hang, not a timing
        answered_while_held = list(answers)
    finally:
        for holder in holders:
            portal.call(limiter.release_on_behalf_of, holder)
        request.join(timeout=20)
    assert answered_while_held == [200]
