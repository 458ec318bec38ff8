"""Issue 14: hostile and careless input gets a 4xx problem and stores nothing, on SQLite and
PostgreSQL: depth headers, paging bounds, control characters, implausible intrinsics, corrupt
JPEGs, depth estimators without depth, and log lines that user strings cannot forge."""

from __future__ import annotations

import io
import json
import logging
import struct

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient
from numpy.lib import format as npy_format
from sqlalchemy import create_engine, func, select

from db.models import FeatureArray, Map, ReferenceImage
from tests.conftest import create_map, image_metadata, upload_view
from tools.synthetic.scene import SyntheticView, encode_depth_png, encode_png

PROBLEM = "application/problem+json"


def _counts(database_url: str) -> tuple[int, int, int]:
    """(maps, images, feature arrays) stored."""
    engine = create_engine(database_url)
    with engine.connect() as conn:
        counts = tuple(
            conn.scalar(select(func.count()).select_from(table)) or 0
            for table in (Map, ReferenceImage, FeatureArray)
        )
    engine.dispose()
    return counts  # type: ignore[return-value]


def _assert_problem(response: object, status: int, kind: str = "invalid-input") -> dict:  # type: ignore[type-arg]
    assert response.status_code == status, response.text  # type: ignore[attr-defined]
    assert response.headers["content-type"] == PROBLEM  # type: ignore[attr-defined]
    problem: dict = response.json()  # type: ignore[attr-defined,type-arg]
    assert problem["type"].endswith("/" + kind) and problem["detail"]
    return problem


def _huge_npy() -> bytes:
    """A 144-byte .npy whose header claims 10⁵ × 10⁵ float32 (40 GB)."""
    buf = io.BytesIO()
    header = {"descr": "<f4", "fortran_order": False, "shape": (100_000, 100_000)}
    npy_format.write_array_header_1_0(buf, header)
    return buf.getvalue() + b"\x00" * 16


def _jpeg(view: SyntheticView) -> bytes:
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(view.image[:, :, ::-1]))
    assert ok
    return buf.tobytes()


def _truncated_jpeg(view: SyntheticView) -> bytes:
    """Cut to a third, with an end-of-image marker appended."""
    data = _jpeg(view)
    return data[: len(data) // 3] + b"\xff\xd9"


def _jpeg_claiming_6000(view: SyntheticView) -> bytes:
    """A 640×480 JPEG whose frame header says 6000×6000."""
    data = bytearray(_jpeg(view))
    sof = data.index(b"\xff\xc0")
    data[sof + 5 : sof + 9] = struct.pack(">HH", 6000, 6000)
    return bytes(data)


def _post_image(
    client: TestClient,
    map_id: str,
    image: bytes,
    metadata: dict[str, object],
    depth: bytes | None = None,
) -> object:
    files = {"image": ("x.jpg", image, "image/jpeg")}
    if depth is not None:
        files["depth"] = ("d.npy", depth, "application/octet-stream")
    return client.post(
        f"/v1/maps/{map_id}/images", files=files, data={"metadata": json.dumps(metadata)}
    )


def _post_localize(
    client: TestClient,
    map_id: str,
    image: bytes,
    params: dict[str, object],
    depth: tuple[str, bytes] | None = None,
) -> object:
    files = {"image": ("q.png", image, "image/png")}
    if depth is not None:
        files["depth"] = (depth[0], depth[1], "application/octet-stream")
    return client.post(
        f"/v1/maps/{map_id}/localize", files=files, data={"params": json.dumps(params)}
    )


# --- 2: a depth header claiming a huge shape is refused before anything is allocated


def test_huge_npy_depth_header_is_422_on_add(
    client: TestClient, database_url: str, reference_views: list[SyntheticView]
) -> None:
    map_id = create_map(client)
    view = reference_views[0]
    response = _post_image(
        client, map_id, encode_png(view.image), image_metadata(view), _huge_npy()
    )
    problem = _assert_problem(response, 422)
    assert "depth map is 100000×100000" in problem["detail"]
    assert _counts(database_url) == (1, 0, 0)


def test_huge_npy_depth_header_is_422_on_localize(
    client: TestClient, query_views: list[SyntheticView]
) -> None:
    map_id = create_map(client)
    response = _post_localize(
        client,
        map_id,
        encode_png(query_views[0].image),
        {"estimator": "e3p1"},
        ("d.npy", _huge_npy()),
    )
    _assert_problem(response, 422)


# --- 3: paging bounds


@pytest.mark.parametrize("query", [{"offset": 2**63}, {"offset": -1}, {"limit": 10**6}])
def test_paging_out_of_bounds_is_422(client: TestClient, query: dict[str, int]) -> None:
    map_id = create_map(client)
    for path in ("/v1/maps", f"/v1/maps/{map_id}/images"):
        _assert_problem(client.get(path, params=query), 422)


def test_largest_offset_is_an_empty_page(client: TestClient) -> None:
    map_id = create_map(client)
    for path in ("/v1/maps", f"/v1/maps/{map_id}/images"):
        response = client.get(path, params={"offset": 2**31 - 1})
        assert response.status_code == 200 and response.json()["items"] == []


# --- 4: control characters in names, descriptions and path ids


@pytest.mark.parametrize("text", ["a\x00b", "a\nb", "a\x1b[31mb", "a\u2028b", "a\x85b"])
def test_control_characters_in_map_fields_are_422(
    client: TestClient, database_url: str, text: str
) -> None:
    problem = _assert_problem(client.post("/v1/maps", json={"name": text}), 422)
    assert problem["errors"][0]["loc"] == ["body", "name"]
    if text != "a\nb":  # a description may hold line breaks
        response = client.post("/v1/maps", json={"name": "m", "description": text})
        problem = _assert_problem(response, 422)
        assert problem["errors"][0]["loc"] == ["body", "description"]
    assert _counts(database_url) == (0, 0, 0)
    multi_line = client.post("/v1/maps", json={"name": "m", "description": "one\ntwo\tthree"})
    assert multi_line.status_code == 201


@pytest.mark.parametrize("name", ["a\x00b", "evil\n2026-01-01 INFO forged", "tab\there"])
def test_control_characters_in_image_name_are_422(
    client: TestClient, database_url: str, reference_views: list[SyntheticView], name: str
) -> None:
    map_id = create_map(client)
    view = reference_views[0]
    response = _post_image(client, map_id, encode_png(view.image), image_metadata(view, name))
    problem = _assert_problem(response, 422)
    assert problem["errors"][0]["loc"] == ["metadata", "name"]
    assert _counts(database_url) == (1, 0, 0)


@pytest.mark.parametrize("bad_id", ["a%00b", "%00", "not-a-uuid", "0" * 36, "Ä" * 3])
def test_path_ids_that_name_no_row_are_404(
    client: TestClient, reference_views: list[SyntheticView], bad_id: str
) -> None:
    """Ids that cannot be stored ids are 404 like unknown ones, without reaching the
    database (PostgreSQL refuses NUL in text)."""
    map_id = create_map(client)
    image_id = upload_view(client, map_id, reference_views[0]).json()["id"]  # type: ignore[attr-defined]
    for method, path in [
        ("GET", f"/v1/maps/{bad_id}"),
        ("DELETE", f"/v1/maps/{bad_id}"),
        ("GET", f"/v1/maps/{bad_id}/images"),
        ("GET", f"/v1/maps/{bad_id}/images/{image_id}"),
        ("GET", f"/v1/maps/{map_id}/images/{bad_id}"),
        ("DELETE", f"/v1/maps/{map_id}/images/{bad_id}"),
        ("POST", f"/v1/maps/{bad_id}/reindex"),
    ]:
        _assert_problem(client.request(method, path), 404, "not-found")
    upload = upload_view(client, bad_id, reference_views[1])
    _assert_problem(upload, 404, "not-found")
    _assert_problem(
        _post_localize(client, bad_id, encode_png(reference_views[1].image), {}), 404, "not-found"
    )


# --- 6: physically implausible intrinsics


def _camera_with(view: SyntheticView, **changes: object) -> dict[str, object]:
    cam = view.camera
    camera: dict[str, object] = {
        "model": "PINHOLE",
        "width": cam.width,
        "height": cam.height,
        "params": list(cam.params),
    }
    camera.update(changes)
    return camera


IMPLAUSIBLE = [
    ({"params": [1e-300, 1e-300, 320.0, 240.0]}, "fx = 1e-300"),
    ({"params": [1e9, 1e9, 320.0, 240.0]}, "fx = 1e+09"),
    ({"params": [500.0, 500.0, 320.0, 1e6]}, "cy = 1e+06"),
    ({"params": [500.0, 500.0, -700.0, 240.0]}, "cx = -700"),
    (
        {"model": "OPENCV", "params": [500.0, 500.0, 320.0, 240.0, 1e6, 0.0, 0.0, 0.0]},
        "k1 = 1e+06",
    ),
    ({"width": 0}, "greater than 0"),
]


@pytest.mark.parametrize(("changes", "fragment"), IMPLAUSIBLE)
def test_implausible_intrinsics_are_422_on_add(
    client: TestClient,
    database_url: str,
    reference_views: list[SyntheticView],
    changes: dict[str, object],
    fragment: str,
) -> None:
    map_id = create_map(client)
    view = reference_views[0]
    metadata = image_metadata(view)
    metadata["camera"] = _camera_with(view, **changes)
    problem = _assert_problem(_post_image(client, map_id, encode_png(view.image), metadata), 422)
    assert fragment in problem["detail"]
    assert problem["errors"][0]["loc"][:2] == ["metadata", "camera"]
    assert _counts(database_url) == (1, 0, 0)


@pytest.mark.parametrize(("changes", "fragment"), IMPLAUSIBLE)
def test_implausible_intrinsics_are_422_on_localize(
    client: TestClient,
    query_views: list[SyntheticView],
    changes: dict[str, object],
    fragment: str,
) -> None:
    map_id = create_map(client)
    view = query_views[0]
    params = {"camera": _camera_with(view, **changes)}
    problem = _assert_problem(_post_localize(client, map_id, encode_png(view.image), params), 422)
    assert fragment in problem["detail"]
    assert problem["errors"][0]["loc"][:2] == ["params", "camera"]


# --- 13: corrupt JPEGs are decoded fully and refused


@pytest.mark.parametrize("corrupt", [_truncated_jpeg, _jpeg_claiming_6000])
def test_corrupt_jpeg_is_422_and_stores_nothing(
    client: TestClient, database_url: str, reference_views: list[SyntheticView], corrupt: object
) -> None:
    map_id = create_map(client)
    view = reference_views[0]
    image = corrupt(view)  # type: ignore[operator]
    metadata = image_metadata(view)
    if corrupt is _jpeg_claiming_6000:
        metadata["camera"] = _camera_with(
            view, width=6000, height=6000, params=[7000.0, 7000.0, 3000.0, 3000.0]
        )
    _assert_problem(_post_image(client, map_id, image, metadata), 422, "invalid-image")
    assert _counts(database_url) == (1, 0, 0)
    _assert_problem(_post_localize(client, map_id, image, {}), 422, "invalid-image")
    # the intact JPEG is fine
    assert _post_image(client, map_id, _jpeg(view), image_metadata(view)).status_code == 201  # type: ignore[attr-defined]


# --- 17: depth estimators without depth


@pytest.mark.parametrize("estimator", ["e3p1", "essential_3pt_depth"])
def test_depth_estimator_without_query_depth_is_422(
    client: TestClient, query_views: list[SyntheticView], estimator: str
) -> None:
    map_id = create_map(client)
    response = _post_localize(
        client, map_id, encode_png(query_views[0].image), {"estimator": estimator}
    )
    problem = _assert_problem(response, 422)
    assert problem["detail"].startswith(f"depth: estimator {estimator} needs")


def test_depth_estimator_with_references_without_depth_says_so(
    client: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    map_id = create_map(client)
    for view in reference_views[:4]:
        assert upload_view(client, map_id, view).status_code == 201  # type: ignore[attr-defined]
    query = query_views[0]
    response = _post_localize(
        client,
        map_id,
        encode_png(query.image),
        {"estimator": "e3p1"},
        ("d.png", encode_depth_png(query.depth)),
    )
    assert response.status_code == 200, response.text  # type: ignore[attr-defined]
    result = response.json()  # type: ignore[attr-defined]
    assert result["localized"] is False and result["reason"] == "missing_depth"


# --- 12: user strings cannot forge log lines


def test_add_logs_no_user_controlled_line_break(
    client: TestClient,
    reference_views: list[SyntheticView],
    caplog: pytest.LogCaptureFixture,
) -> None:
    map_id = create_map(client)
    view = reference_views[0]
    forged = "x\n2026-01-01 00:00:00 INFO app: forged line"
    with caplog.at_level(logging.DEBUG):
        refused = _post_image(client, map_id, encode_png(view.image), image_metadata(view, forged))
        quoted = upload_view(client, map_id, view, name="quote ' and \\ backslash")
        _post_localize(client, f"{map_id}%0Aforged", encode_png(view.image), {})
    assert refused.status_code == 422  # type: ignore[attr-defined]
    assert quoted.status_code == 201  # type: ignore[attr-defined]
    messages = [
        record.getMessage()
        for record in caplog.records
        if record.name.split(".")[0] in ("app", "services", "db")  # not the test's HTTP client
    ]
    assert any("quote" in message for message in messages)
    for message in messages:
        assert "\n" not in message and "forged" not in message, message
