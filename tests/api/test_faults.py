"""Issue "Holds under every fault": values out of their physical range are refused where they
enter (422), a bad stored row never turns into a 500, and oversized images are 413 on add as on
localize; on SQLite and PostgreSQL."""

from __future__ import annotations

import io
import json
import struct
import uuid
import zlib

import numpy as np
import pytest
from fastapi.testclient import TestClient
from numpy.lib import format as npy_format
from prometheus_client.parser import text_string_to_metric_families
from sqlalchemy import create_engine, text, update
from sqlalchemy.engine import make_url

from app.metrics import KNOWN_METHODS
from db.models import Map, ReferenceImage
from services.geo.gps import gps_from_exif
from services.imaging.decode import MAX_DEPTH_M, decode_depth
from services.localization.localizer import Localizer
from tests.conftest import (
    create_map,
    fresh_postgres_database,
    image_metadata,
    make_client,
    upload_view,
)
from tools.synthetic.scene import SyntheticView, encode_png

PROBLEM = "application/problem+json"


def _assert_problem(response: object, status: int, kind: str = "invalid-input") -> dict:  # type: ignore[type-arg]
    assert response.status_code == status, response.text  # type: ignore[attr-defined]
    assert response.headers["content-type"] == PROBLEM  # type: ignore[attr-defined]
    problem: dict = response.json()  # type: ignore[attr-defined,type-arg]
    assert problem["type"].endswith("/" + kind), problem
    assert problem["detail"]
    return problem


def _post_image(
    client: TestClient, map_id: str, image: bytes, metadata: dict[str, object]
) -> object:
    return client.post(
        f"/v1/maps/{map_id}/images",
        files={"image": ("i.png", image, "image/png")},
        data={"metadata": json.dumps(metadata)},
    )


def _localize(client: TestClient, map_id: str, view: SyntheticView, **params: object) -> object:
    return client.post(
        f"/v1/maps/{map_id}/localize",
        files={"image": ("q.png", encode_png(view.image), "image/png")},
        data={"params": json.dumps(params)},
    )


@pytest.mark.parametrize(
    "translation",
    [[1e155, 0.0, 0.0], [1e200, 1e200, 1e200], [0.0, 0.0, 1.0001e7], [6e6, 6e6, 6e6]],
)
def test_translation_beyond_the_physical_range_is_422(
    client: TestClient, reference_views: list[SyntheticView], translation: list[float]
) -> None:
    map_id = create_map(client)
    view = reference_views[0]
    metadata = image_metadata(view)
    metadata["cam_from_world"]["translation"] = translation  # type: ignore[index]
    problem = _assert_problem(_post_image(client, map_id, encode_png(view.image), metadata), 422)
    assert "translation" in problem["detail"] and "1e+07 m" in problem["detail"]
    assert client.get(f"/v1/maps/{map_id}/images").json()["total"] == 0


def test_translation_within_the_physical_range_is_stored(
    client: TestClient, reference_views: list[SyntheticView]
) -> None:
    """A map in Earth-centred coordinates: cameras about 6,400 km from the origin."""
    map_id = create_map(client)
    view = reference_views[0]
    metadata = image_metadata(view)
    metadata["cam_from_world"]["translation"] = [4e6, 3e6, 4e6]  # type: ignore[index]
    response = _post_image(client, map_id, encode_png(view.image), metadata)
    assert response.status_code == 201, response.text  # type: ignore[attr-defined]


@pytest.mark.parametrize("rotation", [[0.0, 0.0, 0.0, 0.0], [2.0, 0.0, 0.0, 0.0]])
def test_rotation_that_is_no_unit_quaternion_is_422(
    client: TestClient, reference_views: list[SyntheticView], rotation: list[float]
) -> None:
    map_id = create_map(client)
    view = reference_views[0]
    metadata = image_metadata(view)
    metadata["cam_from_world"]["rotation"] = rotation  # type: ignore[index]
    problem = _assert_problem(_post_image(client, map_id, encode_png(view.image), metadata), 422)
    assert "unit quaternion" in problem["detail"]


def test_stored_reference_with_an_overflowing_pose_is_left_out_not_500(
    client: TestClient,
    database_url: str,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    """A row stored before poses were range-checked (or written by hand) with a translation
    whose square overflows: auto localizes with the other references instead of failing
    with LinAlgError in the reference layout."""
    map_id = create_map(client)
    ids = []
    for view in reference_views[:6]:
        response = upload_view(client, map_id, view)
        assert response.status_code == 201, response.text  # type: ignore[attr-defined]
        ids.append(response.json()["id"])  # type: ignore[attr-defined]
    engine = create_engine(database_url)
    with engine.begin() as conn:
        conn.execute(
            update(ReferenceImage)
            .where(ReferenceImage.id.in_(ids[:2]))
            .values(tx=1e200, ty=1e200, tz=1e200)
        )
    engine.dispose()
    response = _localize(client, map_id, query_views[0], top_k=6)
    assert response.status_code == 200, response.text  # type: ignore[attr-defined]
    result = response.json()  # type: ignore[attr-defined]
    assert result["localized"], result
    assert all(r["num_matches"] == 0 for r in result["retrieved"] if r["image_id"] in ids[:2])


def _npy(depth: np.ndarray) -> bytes:
    buf = io.BytesIO()
    npy_format.write_array(buf, depth)
    return buf.getvalue()


def test_depth_beyond_the_physical_range_is_unknown() -> None:
    depth = np.full((4, 6), 2.0, np.float32)
    depth[0, 0], depth[1, 1], depth[2, 2] = 1e30, np.inf, MAX_DEPTH_M * 2
    decoded = decode_depth(_npy(depth), 6, 4, 10_000)
    assert decoded[0, 0] == decoded[1, 1] == decoded[2, 2] == 0.0
    assert decoded[3, 3] == 2.0


def _png_claiming(view: SyntheticView, width: int, height: int) -> bytes:
    """A real PNG whose header (with a valid CRC) claims ``width`` × ``height`` pixels."""
    data = bytearray(encode_png(view.image))
    ihdr = bytearray(data[12:29])  # chunk type and data
    ihdr[4:12] = struct.pack(">II", width, height)
    data[12:29] = ihdr
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(ihdr)))
    return bytes(data)


# over 2 × PIL.Image.MAX_IMAGE_PIXELS (178,956,970): Pillow refuses to open it
BOMB = (20_000, 10_000)


def test_image_claiming_more_pixels_than_pillow_opens_is_413_on_add(
    client: TestClient, reference_views: list[SyntheticView]
) -> None:
    map_id = create_map(client)
    view = reference_views[0]
    bomb = _png_claiming(view, *BOMB)
    _assert_problem(_post_image(client, map_id, bomb, image_metadata(view)), 413, "image-too-large")
    assert client.get(f"/v1/maps/{map_id}/images").json()["total"] == 0
    localized = client.post(
        f"/v1/maps/{map_id}/localize", files={"image": ("q.png", bomb, "image/png")}
    )
    _assert_problem(localized, 413, "image-too-large")


def test_exif_of_a_decompression_bomb_is_none(reference_views: list[SyntheticView]) -> None:
    assert gps_from_exif(_png_claiming(reference_views[0], *BOMB)) is None


def test_made_up_methods_add_no_metric_series(client: TestClient) -> None:
    """A client may send any token as the method: each is counted as ``other``."""
    for i in range(20):
        response = client.request(f"X{i}FOO", "/v1/health")
        assert response.status_code in (400, 404, 405), response.text
    client.request("BREW", f"/no/such/{uuid.uuid4()}")
    scraped = client.get("/metrics")
    assert scraped.status_code == 200
    families = {f.name: f.samples for f in text_string_to_metric_families(scraped.text)}
    requests = [s for s in families["slloc_http_requests"] if s.name.endswith("_total")]
    methods = {s.labels["method"] for s in requests}
    assert methods <= KNOWN_METHODS | {"other"}, methods
    assert sum(s.value for s in requests if s.labels["method"] == "other") == 21
    routes = {s.labels["route"] for s in requests}
    assert all(r.startswith("/") or r == "unmatched" for r in routes), routes
    assert not any("/no/such" in r for r in routes)


REGISTRATION = {
    "origin": {"latitude": 47.3769, "longitude": 8.5417, "height": 408.0},
    "enu_from_map": {"rotation": [1.0, 0.0, 0.0, 0.0], "translation": [3.0, -2.0, 1.0]},
    "scale": 1.0,
}


@pytest.mark.parametrize(
    ("change", "named"),
    [
        ({"origin": {"latitude": 0.0, "longitude": 0.0, "height": 1e308}}, "height"),
        ({"origin": {"latitude": 0.0, "longitude": 0.0, "height": -1e7}}, "height"),
        ({"origin": {"latitude": 0.0, "longitude": 0.0, "height": 100_001.0}}, "height"),
        ({"scale": 1e308}, "scale"),
        ({"scale": 1e-9}, "scale"),
        ({"enu_from_map": {"translation": [1e308, 0.0, 0.0]}}, "translation"),
        ({"enu_from_map": {"translation": [9e6, 9e6, 0.0]}}, "translation"),
    ],
)
def test_geo_registration_out_of_the_physical_range_is_422(
    client: TestClient, change: dict[str, object], named: str
) -> None:
    map_id = create_map(client)
    url = f"/v1/maps/{map_id}/geo-registration"
    problem = _assert_problem(client.put(url, json={**REGISTRATION, **change}), 422)
    assert named in problem["detail"]
    assert client.get(url).status_code == 404
    assert client.put(url, json=REGISTRATION).status_code == 200


def test_gps_height_out_of_the_physical_range_is_422(
    client: TestClient, reference_views: list[SyntheticView]
) -> None:
    map_id = create_map(client)
    view = reference_views[0]
    metadata = {**image_metadata(view), "gps": {"latitude": 1.0, "longitude": 2.0, "height": 1e308}}
    problem = _assert_problem(_post_image(client, map_id, encode_png(view.image), metadata), 422)
    assert "height" in problem["detail"]


def test_stored_registration_out_of_range_gives_no_geopose_not_nulls(
    client: TestClient,
    database_url: str,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    """A registration stored before its values were range-checked: localize answers without
    a geopose (the schema's numbers are never null) and reading it is 404."""
    map_id = create_map(client)
    for view in reference_views[:6]:
        assert upload_view(client, map_id, view).status_code == 201
    document = {
        "origin": [47.0, 8.0, 1e308],
        "rotation": [1.0, 0.0, 0.0, 0.0],
        "translation": [0.0, 0.0, 0.0],
        "scale": 1e308,
        "source": "manual",
    }
    engine = create_engine(database_url)
    with engine.begin() as conn:
        conn.execute(update(Map).where(Map.id == map_id).values(geo_registration=document))
    engine.dispose()
    response = _localize(client, map_id, query_views[0], top_k=6)
    assert response.status_code == 200, response.text  # type: ignore[attr-defined]
    result = response.json()  # type: ignore[attr-defined]
    assert result["localized"] and result["geopose"] is None, result["geopose"]
    assert client.get(f"/v1/maps/{map_id}/geo-registration").status_code == 404


# a PostgreSQL URL on a port nothing listens on: every connection is refused
CLOSED_PORT_URL = "postgresql+psycopg://postgres@127.0.0.1:9/slloc"


def test_database_outage_is_503_with_retry_after_and_probes_tell(localizer: Localizer) -> None:
    with make_client(
        CLOSED_PORT_URL, localizer, raise_server_exceptions=False, auto_migrate=False
    ) as c:
        for response in (c.get("/v1/maps"), c.post("/v1/maps", json={"name": "m"})):
            problem = _assert_problem(response, 503, "database-unavailable")
            assert response.headers["retry-after"] == "5"  # type: ignore[attr-defined]
            assert "password" not in problem["detail"]
        assert c.get("/livez").status_code == 200
        assert c.head("/livez").status_code == 200
        ready = c.get("/readyz")
        assert ready.status_code == 503 and "database" in ready.text
        assert ready.headers["retry-after"]
        assert c.get("/v1/health").json()["status"] == "degraded"


def test_probes_and_head_of_health_answer_200(client: TestClient) -> None:
    for path in ("/livez", "/readyz", "/v1/health"):
        assert client.get(path).status_code == 200, path
        response = client.head(path)
        assert response.status_code == 200, (path, response.status_code)
        assert response.content == b""


@pytest.mark.parametrize("name", ["   ", "\u00a0\u2003", "invoice\u202egpj.exe", "a\u2066b"])
def test_blank_names_and_bidi_controls_are_422(client: TestClient, name: str) -> None:
    _assert_problem(client.post("/v1/maps", json={"name": name}), 422)


@pytest.mark.parametrize("bad", ["500", True])
def test_camera_params_must_be_numbers(
    client: TestClient, reference_views: list[SyntheticView], bad: object
) -> None:
    map_id = create_map(client)
    view = reference_views[0]
    metadata = image_metadata(view)
    params = list(metadata["camera"]["params"])  # type: ignore[index]
    params[0] = bad
    metadata["camera"] = {**metadata["camera"], "params": params}  # type: ignore[dict-item]
    _assert_problem(_post_image(client, map_id, encode_png(view.image), metadata), 422)


@pytest.mark.postgres
def test_read_only_postgres_refuses_writes_with_503_and_serves_reads(
    postgres_admin_url: str, localizer: Localizer
) -> None:
    """A database turned read-only (as a hot standby is): writes are 503
    database-not-writable with Retry-After, reads are served, and writes work again once it
    is writable, without a restart."""
    database = next(fresh := fresh_postgres_database(postgres_admin_url))
    name = make_url(database).database
    admin = create_engine(postgres_admin_url, isolation_level="AUTOCOMMIT")

    def read_only(on: bool) -> None:
        with admin.connect() as conn:
            conn.execute(text(f'ALTER DATABASE "{name}" SET default_transaction_read_only = {on}'))
            # the pool's connections end: new ones read the setting (pre-ping reconnects)
            conn.execute(
                text(
                    "SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                    "WHERE datname = :name AND pid <> pg_backend_pid()"
                ),
                {"name": name},
            )

    try:
        with make_client(database, localizer, raise_server_exceptions=False) as c:
            map_id = create_map(c)
            read_only(True)
            for response in (
                c.post("/v1/maps", json={"name": "refused"}),
                c.delete(f"/v1/maps/{map_id}"),
            ):
                problem = _assert_problem(response, 503, "database-not-writable")
                assert response.headers["retry-after"] == "5"  # type: ignore[attr-defined]
                assert "reads are still served" in problem["detail"]
            listed = c.get("/v1/maps")
            assert listed.status_code == 200 and listed.json()["total"] == 1
            read_only(False)
            assert c.post("/v1/maps", json={"name": "accepted"}).status_code == 201
    finally:
        admin.dispose()
        fresh.close()
