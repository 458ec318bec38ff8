"""Reference images: add, list, get, delete, and bad input that must store nothing."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import create_engine, func, select

from db.models import FeatureArray, ReferenceImage
from tests.conftest import create_map, image_metadata, make_client, upload_view
from tools.synthetic.scene import SyntheticView, encode_depth_png, encode_png

PROBLEM = "application/problem+json"


def _counts(database_url: str) -> tuple[int, int]:
    engine = create_engine(database_url)
    with engine.connect() as conn:
        images = conn.scalar(select(func.count()).select_from(ReferenceImage)) or 0
        arrays = conn.scalar(select(func.count()).select_from(FeatureArray)) or 0
    engine.dispose()
    return images, arrays


def test_add_get_list_delete(
    client: TestClient, database_url: str, reference_views: list[SyntheticView]
) -> None:
    map_id = create_map(client)
    view = reference_views[0]
    response = upload_view(client, map_id, view)
    assert response.status_code == 201, response.text
    image = response.json()
    assert image["name"] == view.name
    assert image["num_keypoints"] > 500
    assert image["has_depth"] is False
    assert image["camera"]["params"] == list(view.camera.params)
    q = np.array(image["cam_from_world"]["rotation"])
    assert np.allclose(np.abs(q @ view.cam_from_world.quaternion), 1.0, atol=1e-9)
    assert np.allclose(image["cam_from_world"]["translation"], view.cam_from_world.translation)

    assert client.get(f"/v1/maps/{map_id}/images/{image['id']}").json() == image
    upload_view(client, map_id, reference_views[1])
    page = client.get(f"/v1/maps/{map_id}/images", params={"limit": 1}).json()
    assert page["total"] == 2 and len(page["items"]) == 1
    assert _counts(database_url) == (2, 8)

    assert client.delete(f"/v1/maps/{map_id}/images/{image['id']}").status_code == 204
    assert client.get(f"/v1/maps/{map_id}/images/{image['id']}").status_code == 404
    assert _counts(database_url) == (1, 4)  # its four feature arrays are gone too


def test_add_with_depth(client: TestClient, reference_views: list[SyntheticView]) -> None:
    map_id = create_map(client)
    view = reference_views[0]
    response = client.post(
        f"/v1/maps/{map_id}/images",
        files={
            "image": ("a.png", encode_png(view.image), "image/png"),
            "depth": ("a_depth.png", encode_depth_png(view.depth), "image/png"),
        },
        data={"metadata": json.dumps(image_metadata(view))},
    )
    assert response.status_code == 201, response.text
    assert response.json()["has_depth"] is True


def test_duplicate_name_is_409(client: TestClient, reference_views: list[SyntheticView]) -> None:
    map_id = create_map(client)
    assert upload_view(client, map_id, reference_views[0], name="a").status_code == 201
    response = upload_view(client, map_id, reference_views[1], name="a")
    assert response.status_code == 409
    assert response.headers["content-type"] == PROBLEM
    # the same name in another map is fine
    other = create_map(client, "other")
    assert upload_view(client, other, reference_views[1], name="a").status_code == 201


def test_unknown_map_or_image_is_404(
    client: TestClient, reference_views: list[SyntheticView]
) -> None:
    assert upload_view(client, "missing", reference_views[0]).status_code == 404
    map_id = create_map(client)
    for response in (
        client.get(f"/v1/maps/{map_id}/images/missing"),
        client.delete(f"/v1/maps/{map_id}/images/missing"),
        client.get("/v1/maps/missing/images"),
    ):
        assert response.status_code == 404
        assert response.headers["content-type"] == PROBLEM


def _post(client: TestClient, map_id: str, image: bytes, metadata: object) -> object:
    return client.post(
        f"/v1/maps/{map_id}/images",
        files={"image": ("x.png", image, "image/png")},
        data={"metadata": metadata if isinstance(metadata, str) else json.dumps(metadata)},
    )


def _bad_metadata(view: SyntheticView) -> dict[str, object]:
    base = image_metadata(view)
    wrong_params = json.loads(json.dumps(base))
    wrong_params["camera"]["params"] = [500.0, 320.0]
    non_unit = json.loads(json.dumps(base))
    non_unit["cam_from_world"]["rotation"] = [1.0, 0.5, 0.0, 0.0]
    wrong_size = json.loads(json.dumps(base))
    wrong_size["camera"]["width"] = 1000
    return {"wrong_params": wrong_params, "non_unit": non_unit, "wrong_size": wrong_size}


@pytest.mark.parametrize(
    "case",
    [
        "corrupt_image",
        "truncated_png",
        "not_json",
        "wrong_params",
        "non_unit",
        "nan_quaternion",
        "wrong_size",
    ],
)
def test_bad_input_is_422_and_stores_nothing(
    client: TestClient, database_url: str, reference_views: list[SyntheticView], case: str
) -> None:
    map_id = create_map(client)
    view = reference_views[0]
    png = encode_png(view.image)
    image, metadata = png, image_metadata(view)
    if case == "corrupt_image":
        image = b"\xff\xd8\xff\xe0" + b"garbage" * 100
    elif case == "truncated_png":
        image = png[: len(png) // 3]
    elif case == "not_json":
        metadata = "{not json"  # type: ignore[assignment]
    elif case == "nan_quaternion":
        metadata = json.dumps(metadata).replace(
            str(metadata["cam_from_world"]["rotation"][0]),
            "NaN",
            1,  # type: ignore[index]
        )
    elif case in ("wrong_params", "non_unit", "wrong_size"):
        metadata = _bad_metadata(view)[case]
    response = _post(client, map_id, image, metadata)
    assert response.status_code == 422, response.text  # type: ignore[attr-defined]
    assert response.headers["content-type"] == PROBLEM  # type: ignore[attr-defined]
    problem = response.json()  # type: ignore[attr-defined]
    assert problem["status"] == 422 and problem["detail"]
    assert _counts(database_url) == (0, 0)


def test_oversized_upload_is_413_and_stores_nothing(
    database_url: str, localizer: object, reference_views: list[SyntheticView]
) -> None:
    with make_client(database_url, localizer, max_upload_bytes=100_000) as client:  # type: ignore[arg-type]
        map_id = create_map(client)
        response = upload_view(client, map_id, reference_views[0])  # ~600 kB PNG
        assert response.status_code == 413  # type: ignore[attr-defined]
        assert response.headers["content-type"] == PROBLEM  # type: ignore[attr-defined]
    assert _counts(database_url) == (0, 0)


def test_too_many_pixels_is_413(database_url: str, localizer: object) -> None:
    import cv2

    big = np.zeros((3000, 4000, 3), np.uint8)
    ok, buf = cv2.imencode(".jpg", big)
    assert ok
    with make_client(database_url, localizer) as client:  # type: ignore[arg-type]
        map_id = create_map(client)
        meta = {
            "name": "big",
            "camera": {
                "model": "PINHOLE",
                "width": 4000,
                "height": 3000,
                "params": [3000, 3000, 2000, 1500],
            },
            "cam_from_world": {"rotation": [1, 0, 0, 0], "translation": [0, 0, 0]},
        }
        client.app.state.localizers.served.max_pixels = 1_000_000  # type: ignore[attr-defined]
        try:
            response = _post(client, map_id, buf.tobytes(), meta)
        finally:
            client.app.state.localizers.served.max_pixels = 40_000_000  # type: ignore[attr-defined]
        assert response.status_code == 413  # type: ignore[attr-defined]
        assert response.json()["type"].endswith("/image-too-large")  # type: ignore[attr-defined]
    assert _counts(database_url) == (0, 0)


def test_failure_half_way_leaves_nothing(
    database_url: str,
    localizer: object,
    reference_views: list[SyntheticView],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The image row is flushed, then writing the features fails: no row and no features."""
    import db.repositories.images as images_module

    client = make_client(database_url, localizer, raise_server_exceptions=False)  # type: ignore[arg-type]
    client.__enter__()
    map_id = create_map(client)
    real_to_row = images_module.to_row
    calls = {"n": 0}

    def failing_to_row(*args: object, **kwargs: object) -> object:
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("disk full (simulated)")
        return real_to_row(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(images_module, "to_row", failing_to_row)
    response = upload_view(client, map_id, reference_views[0])
    assert response.status_code == 500
    assert response.headers["content-type"] == PROBLEM
    assert _counts(database_url) == (0, 0)
    monkeypatch.setattr(images_module, "to_row", real_to_row)
    assert upload_view(client, map_id, reference_views[0]).status_code == 201
    assert _counts(database_url) == (1, 4)
    client.__exit__(None, None, None)


def test_depth_of_wrong_size_is_422(
    client: TestClient, reference_views: list[SyntheticView]
) -> None:
    map_id = create_map(client)
    view = reference_views[0]
    buf = io.BytesIO()
    np.save(buf, np.ones((10, 10), np.float32))
    response = client.post(
        f"/v1/maps/{map_id}/images",
        files={
            "image": ("a.png", encode_png(view.image), "image/png"),
            "depth": ("d.npy", buf.getvalue(), "application/octet-stream"),
        },
        data={"metadata": json.dumps(image_metadata(view))},
    )
    assert response.status_code == 422
    assert "depth map is 10×10" in response.json()["detail"]
