"""GET /v1/maps/{map_id}/images/{image_id}/preview: the JPEG kept of each reference image for
display, bounded in size, gone with its image, behind the client role."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import create_engine, func, select

from db.models import ReferencePreview
from services.imaging.preview import make_preview
from services.localization.localizer import Localizer
from tests.conftest import create_map, make_client, upload_view
from tools.synthetic.scene import SyntheticView

PROBLEM = "application/problem+json"


def _decode(jpeg: bytes) -> np.ndarray:
    bgr = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert bgr is not None
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _preview_rows(database_url: str) -> int:
    engine = create_engine(database_url)
    with engine.connect() as conn:
        count = conn.scalar(select(func.count()).select_from(ReferencePreview)) or 0
    engine.dispose()
    return count


def test_preview_is_the_image_and_goes_with_it(
    client: TestClient, database_url: str, reference_views: list[SyntheticView]
) -> None:
    map_id = create_map(client)
    view = reference_views[0]
    image_id = upload_view(client, map_id, view).json()["id"]
    response = client.get(f"/v1/maps/{map_id}/images/{image_id}/preview")
    assert response.status_code == 200
    assert response.headers["content-type"] == "image/jpeg"
    preview = _decode(response.content)
    assert preview.shape == view.image.shape  # 640×480 is under the default bound: kept
    # a JPEG of the same pixels: far closer to them than to another view's
    error = np.abs(preview.astype(float) - view.image).mean()
    assert error < 8.0
    assert np.abs(preview.astype(float) - reference_views[5].image).mean() > 3 * error

    other = create_map(client, "other")
    assert client.get(f"/v1/maps/{other}/images/{image_id}/preview").status_code == 404
    assert client.delete(f"/v1/maps/{map_id}/images/{image_id}").status_code == 204
    gone = client.get(f"/v1/maps/{map_id}/images/{image_id}/preview")
    assert gone.status_code == 404
    assert gone.headers["content-type"] == PROBLEM
    assert _preview_rows(database_url) == 0


def test_preview_size_setting(
    database_url: str, localizer: Localizer, reference_views: list[SyntheticView]
) -> None:
    view = reference_views[1]
    with make_client(database_url, localizer, preview_max_side=160) as client:
        map_id = create_map(client)
        image_id = upload_view(client, map_id, view).json()["id"]
        preview = _decode(client.get(f"/v1/maps/{map_id}/images/{image_id}/preview").content)
        assert preview.shape == (120, 160, 3)  # 640×480 shrunk to a longer side of 160
    with make_client(database_url, localizer, preview_max_side=0) as client:
        image_id = upload_view(client, map_id, reference_views[2]).json()["id"]
        response = client.get(f"/v1/maps/{map_id}/images/{image_id}/preview")
        assert response.status_code == 404
        assert response.headers["content-type"] == PROBLEM
        assert "preview" in response.json()["detail"]
        assert client.get(f"/v1/maps/{map_id}/images/{image_id}").status_code == 200


def test_preview_needs_a_key_when_auth_is_on(
    database_url: str, localizer: Localizer, reference_views: list[SyntheticView]
) -> None:
    keys = {"X-API-Key": "admin-key"}
    with make_client(database_url, localizer, api_keys="admin-key:admin,client-key:client") as c:
        map_id = c.post("/v1/maps", json={"name": "m"}, headers=keys).json()["id"]
        image_id = upload_view(c, map_id, reference_views[0], headers=keys).json()["id"]
        path = f"/v1/maps/{map_id}/images/{image_id}/preview"
        assert c.get(path).status_code == 401
        assert c.get(path, headers={"X-API-Key": "client-key"}).status_code == 200


@pytest.mark.parametrize(
    ("width", "height", "max_side", "expected"),
    [
        (640, 480, 1024, (480, 640)),  # never enlarged
        (640, 480, 320, (240, 320)),
        (300, 900, 100, (100, 33)),  # portrait: the height is the longer side
    ],
)
def test_make_preview_bounds_the_longer_side(
    width: int, height: int, max_side: int, expected: tuple[int, int]
) -> None:
    image = np.random.default_rng(0).integers(0, 255, (height, width, 3), dtype=np.uint8)
    preview = make_preview(image, max_side)
    assert (preview.height, preview.width) == expected
    assert _decode(preview.jpeg).shape[:2] == expected


def test_make_preview_refuses_a_non_positive_bound() -> None:
    with pytest.raises(ValueError, match="max_side"):
        make_preview(np.zeros((4, 4, 3), np.uint8), 0)
