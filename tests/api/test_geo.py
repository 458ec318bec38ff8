"""Maps on the globe through the API: the geo-registration set by hand and estimated from
reference GPS, GeoPose answers, GPS hints and the GeoPose Protocol, on a rendered scene placed
in Zürich with its z axis pointing North."""

from __future__ import annotations

import base64
import io
import json

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import ExifTags, Image

from services.geo.geodesy import Geodetic, ecef_from_enu_rotation, ecef_from_geodetic
from services.geo.geopose import CV_FROM_GL
from services.geo.registration import GeoRegistration
from services.geometry.rigid import quaternion_to_matrix, rotation_error_deg
from tests.conftest import create_map, image_metadata
from tools.synthetic.scene import SyntheticView, encode_png, unrelated_image

PROBLEM = "application/problem+json"
ORIGIN = Geodetic(47.3769, 8.5417, 408.0)
# scene frame (x right, y down, z forward) → ENU: x East, z North, y down = −Up; a 30° yaw
_YAW = np.radians(30.0)
ENU_FROM_SCENE = np.array(
    [[np.cos(_YAW), -np.sin(_YAW), 0], [np.sin(_YAW), np.cos(_YAW), 0], [0, 0, 1]]
) @ np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
TRUTH = GeoRegistration(ORIGIN, ENU_FROM_SCENE, np.array([3.0, -2.0, 1.0]), 1.0)
REGISTRATION_BODY = {
    "origin": {"latitude": ORIGIN.latitude, "longitude": ORIGIN.longitude, "height": 408.0},
    "enu_from_map": {
        "rotation": [float(v) for v in TRUTH.quaternion],
        "translation": [3.0, -2.0, 1.0],
    },
    "scale": 1.0,
}


def _gps(view: SyntheticView, rng: np.random.Generator, sigma: float) -> dict[str, float]:
    enu = TRUTH.enu_from_map(view.cam_from_world.center[None])[0] + rng.normal(0, sigma, 3)
    lat, lon, h = TRUTH.geodetic_from_map(TRUTH.map_from_enu(enu[None]))[0]
    return {"latitude": lat, "longitude": lon, "height": h, "accuracy_m": max(sigma, 0.01)}


def _add(client: TestClient, map_id: str, view: SyntheticView, gps: dict[str, float] | None):
    metadata = image_metadata(view)
    if gps is not None:
        metadata["gps"] = gps
    return client.post(
        f"/v1/maps/{map_id}/images",
        files={"image": (view.name, encode_png(view.image), "image/png")},
        data={"metadata": json.dumps(metadata)},
    )


@pytest.fixture
def geo_map(client: TestClient, reference_views: list[SyntheticView]) -> str:
    """The scene's references, each with a GPS position 5 cm (1-σ) off the truth."""
    map_id = create_map(client, "zurich")
    rng = np.random.default_rng(0)
    for view in reference_views:
        assert _add(client, map_id, view, _gps(view, rng, 0.05)).status_code == 201
    return map_id


def _camera(view: SyntheticView) -> dict[str, object]:
    return image_metadata(view)["camera"]  # type: ignore[return-value]


def _localize(client: TestClient, map_id: str, view: SyntheticView, **params: object) -> dict:  # type: ignore[type-arg]
    response = client.post(
        f"/v1/maps/{map_id}/localize",
        files={"image": ("q.png", encode_png(view.image), "image/png")},
        data={"params": json.dumps({"camera": _camera(view), **params})},
    )
    assert response.status_code == 200, response.text
    return response.json()  # type: ignore[no-any-return]


def _geopose_errors(geopose: dict, view: SyntheticView) -> tuple[float, float]:  # type: ignore[type-arg]
    """Metres and degrees between a GeoPose answer and the view's true GeoPose (in ECEF)."""
    p = geopose["position"]
    got = ecef_from_geodetic(np.array([[p["lat"], p["lon"], p["h"]]]))[0]
    center = view.cam_from_world.center
    expected = ecef_from_geodetic(TRUTH.geodetic_from_map(center[None]))[0]
    q = geopose["quaternion"]
    enu_from_cam = quaternion_to_matrix(np.array([q["w"], q["x"], q["y"], q["z"]]))
    ecef_from_cam = ecef_from_enu_rotation(Geodetic(p["lat"], p["lon"], p["h"])) @ enu_from_cam
    true_ecef_from_cam = (
        ecef_from_enu_rotation(ORIGIN)
        @ ENU_FROM_SCENE
        @ view.cam_from_world.rotation.T
        @ CV_FROM_GL
    )
    return float(np.linalg.norm(got - expected)), rotation_error_deg(
        ecef_from_cam, true_ecef_from_cam
    )


def test_registration_set_read_and_removed(client: TestClient) -> None:
    map_id = create_map(client)
    assert client.get(f"/v1/maps/{map_id}/geo-registration").status_code == 404
    response = client.put(f"/v1/maps/{map_id}/geo-registration", json=REGISTRATION_BODY)
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["source"] == "manual" and body["position_sigma_m"] == 0.0
    np.testing.assert_allclose(body["enu_from_map"]["rotation"], TRUTH.quaternion, atol=1e-12)
    assert client.get(f"/v1/maps/{map_id}/geo-registration").json() == body
    assert client.delete(f"/v1/maps/{map_id}/geo-registration").status_code == 204
    assert client.get(f"/v1/maps/{map_id}/geo-registration").status_code == 404
    assert client.delete(f"/v1/maps/{map_id}/geo-registration").status_code == 404


@pytest.mark.parametrize(
    "change",
    [
        {"origin": {"latitude": 91.0, "longitude": 0.0}},
        {"scale": 0.0},
        {"enu_from_map": {"rotation": [0, 0, 0, 0], "translation": [0, 0, 0]}},
        {"enu_from_map": {"rotation": [1, 0, 0], "translation": [0, 0, 0]}},
    ],
)
def test_bad_registration_is_422_and_keeps_the_stored_one(
    client: TestClient, change: dict[str, object]
) -> None:
    map_id = create_map(client)
    client.put(f"/v1/maps/{map_id}/geo-registration", json=REGISTRATION_BODY)
    response = client.put(
        f"/v1/maps/{map_id}/geo-registration", json={**REGISTRATION_BODY, **change}
    )
    assert response.status_code == 422, response.text
    assert response.headers["content-type"] == PROBLEM
    assert client.get(f"/v1/maps/{map_id}/geo-registration").json()["source"] == "manual"


def test_unknown_map_is_404(client: TestClient) -> None:
    missing = "00000000-0000-0000-0000-000000000000"
    assert (
        client.put(f"/v1/maps/{missing}/geo-registration", json=REGISTRATION_BODY).status_code
        == 404
    )
    assert client.post(f"/v1/maps/{missing}/geo-registration/estimate").status_code == 404


def test_estimate_needs_references_with_gps(
    client: TestClient, reference_views: list[SyntheticView]
) -> None:
    map_id = create_map(client)
    for view in reference_views[:3]:
        assert _add(client, map_id, view, None).status_code == 201
    response = client.post(f"/v1/maps/{map_id}/geo-registration/estimate")
    assert response.status_code == 422
    assert "at least 3" in response.json()["detail"]


def test_estimated_registration_and_geopose(
    client: TestClient, geo_map: str, query_views: list[SyntheticView]
) -> None:
    """GPS at 5 cm on the 24 references: the estimate reproduces the truth closely, and a
    localized query's GeoPose is within a few centimetres of its true GeoPose."""
    response = client.post(
        f"/v1/maps/{geo_map}/geo-registration/estimate", json={"max_error_m": 0.5}
    )
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["source"] == "estimated"
    assert body["num_references"] == body["num_inliers"] == 24
    assert len(body["residuals"]) == 24 and all(r["inlier"] for r in body["residuals"])
    assert 0.03 < body["residual_rms_m"] < 0.15  # 3-D residuals of σ = 5 cm per axis
    assert body["scale"] == pytest.approx(1.0, abs=0.02)
    result = _localize(client, geo_map, query_views[0])
    assert result["localized"], result
    position, rotation = _geopose_errors(result["geopose"], query_views[0])
    assert position < 0.1 and rotation < 1.0, (position, rotation)
    assert result["geopose_accuracy"]["horizontal_m"] > 0


def test_given_registration_geopose_within_a_centimetre(
    client: TestClient, geo_map: str, query_views: list[SyntheticView]
) -> None:
    client.put(f"/v1/maps/{geo_map}/geo-registration", json=REGISTRATION_BODY)
    result = _localize(client, geo_map, query_views[1])
    assert result["localized"], result
    position, rotation = _geopose_errors(result["geopose"], query_views[1])
    assert position < 0.01 and rotation < 0.2, (position, rotation)
    maps_without = create_map(client, "flat")
    assert "geopose" not in _localize(client, maps_without, query_views[1]) or (
        _localize(client, maps_without, query_views[1])["geopose"] is None
    )


def test_gps_hint_narrows_retrieval(
    client: TestClient, geo_map: str, query_views: list[SyntheticView]
) -> None:
    view = query_views[2]
    fix = _gps(view, np.random.default_rng(1), 2.0)
    fix["accuracy_m"] = 5.0
    assert client.get(f"/v1/maps/{geo_map}/geo-registration").status_code == 404
    response = client.post(
        f"/v1/maps/{geo_map}/localize",
        files={"image": ("q.png", encode_png(view.image), "image/png")},
        data={"params": json.dumps({"gps": fix})},
    )
    assert response.status_code == 422 and "geo-registration" in response.json()["detail"]

    client.put(f"/v1/maps/{geo_map}/geo-registration", json=REGISTRATION_BODY)
    near = _localize(client, geo_map, view, gps=fix)
    assert near["localized"], near
    far = TRUTH.geodetic_from_map(TRUTH.map_from_enu(np.array([[1000.0, 0.0, 0.0]])))[0]
    away = {"latitude": far[0], "longitude": far[1], "accuracy_m": 5.0}
    result = _localize(client, geo_map, view, gps=away)
    assert not result["localized"] and result["reason"] == "no_references"
    response = client.post(
        f"/v1/maps/{geo_map}/localize",
        files={"image": ("q.png", encode_png(view.image), "image/png")},
        data={"params": json.dumps({"gps": fix, "prior": {"position": [0, 0, 0], "radius": 1}})},
    )
    assert response.status_code == 422


def test_exif_gps_is_kept_on_add(client: TestClient, reference_views: list[SyntheticView]) -> None:
    view = reference_views[0]
    image = Image.fromarray(view.image)
    exif = Image.Exif()
    exif.get_ifd(ExifTags.IFD.GPSInfo).update(
        {1: "N", 2: (47.0, 22.0, 36.84), 3: "E", 4: (8.0, 32.0, 30.12), 6: 410.0}
    )
    buffer = io.BytesIO()
    image.save(buffer, "JPEG", quality=95, exif=exif)
    map_id = create_map(client)
    response = client.post(
        f"/v1/maps/{map_id}/images",
        files={"image": ("ref.jpg", buffer.getvalue(), "image/jpeg")},
        data={"metadata": json.dumps(image_metadata(view))},
    )
    assert response.status_code == 201, response.text
    gps = response.json()["gps"]
    assert gps["latitude"] == pytest.approx(47.3769) and gps["longitude"] == pytest.approx(8.5417)
    assert gps["height"] == pytest.approx(410.0)


def _gpp_request(view: SyntheticView, image_format: str = "PNG") -> dict[str, object]:
    if image_format == "RGBA32":
        data = cv2.cvtColor(view.image, cv2.COLOR_RGB2RGBA).tobytes()
    else:
        data = encode_png(view.image)
    cam = view.camera
    return {
        "id": "req-1",
        "timestamp": 1_700_000_000_000,
        "type": "geopose",
        "sensors": [{"id": "cam0", "type": "camera"}],
        "sensorReadings": {
            "cameraReadings": [
                {
                    "sequenceNumber": 0,
                    "imageFormat": image_format,
                    "size": [cam.width, cam.height],
                    "imageBytes": base64.b64encode(data).decode(),
                    "params": {"model": cam.model, "modelParams": list(cam.params)},
                    "privacy": {"dataRetention": []},
                }
            ],
        },
    }


@pytest.mark.parametrize("image_format", ["PNG", "RGBA32"])
def test_geopose_protocol(
    client: TestClient, geo_map: str, query_views: list[SyntheticView], image_format: str
) -> None:
    view = query_views[1]
    request = _gpp_request(view, image_format)
    response = client.post(f"/v1/maps/{geo_map}/geopose", json=request)
    assert response.status_code == 422 and response.json()["type"].endswith("not-geo-registered")
    client.put(f"/v1/maps/{geo_map}/geo-registration", json=REGISTRATION_BODY)
    response = client.post(f"/v1/maps/{geo_map}/geopose?camera_axes=opengl", json=request)
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["id"] == "req-1" and body["type"] == "geopose"
    assert set(body["accuracy"]) == {"position", "orientation"}
    position, rotation = _geopose_errors(body["geopose"], view)
    assert position < 0.01 and rotation < 0.2, (position, rotation)


def test_geopose_protocol_errors(
    client: TestClient, geo_map: str, query_views: list[SyntheticView]
) -> None:
    client.put(f"/v1/maps/{geo_map}/geo-registration", json=REGISTRATION_BODY)
    url = f"/v1/maps/{geo_map}/geopose"
    request = _gpp_request(query_views[0])
    reading = request["sensorReadings"]["cameraReadings"][0]  # type: ignore[index]
    not_an_image = base64.b64encode(bytes(1000)).decode()
    for change, needle in (
        ({"imageBytes": "***"}, "base64"),
        ({"imageFormat": "YUV420", "imageBytes": not_an_image}, "imageFormat"),
        ({"imageFormat": "PNG", "imageBytes": not_an_image}, "neither JPEG nor PNG"),
        ({"imageFormat": "RGBA32", "size": [640, 480], "imageBytes": not_an_image}, "bytes"),
        ({"imageFormat": "RGBA32", "size": None, "imageBytes": not_an_image}, "size"),
        ({"params": {"model": "FISHEYE", "modelParams": [1.0]}}, "model"),
    ):
        bad = json.loads(json.dumps(request))
        bad["sensorReadings"]["cameraReadings"][0] = {**reading, **change}
        response = client.post(url, json=bad)
        assert response.status_code == 422, (change, response.text)
        assert response.headers["content-type"] == PROBLEM
        assert needle in response.json()["detail"], (needle, response.json())
    unrelated = json.loads(json.dumps(request))
    unrelated["sensorReadings"]["cameraReadings"][0]["imageBytes"] = base64.b64encode(
        encode_png(unrelated_image(5))
    ).decode()
    response = client.post(url, json=unrelated)
    assert response.status_code == 404, response.text
    assert response.json()["type"].endswith("not-localized")
