"""The GeoPose Protocol endpoint against requests shaped exactly as the field's published
clients send them: Open AR Cloud's Python demo client (oscp-geopose-protocol, version 2, and
the version 1 shape of the protocol's spec), and @oarc/gpp-access 0.2.1 as sparcl builds it.
One geo-registered map of the synthetic scene (placed in Zürich, tests/api/test_geo.py) serves
every test of the module; answers are checked against the scene's ground truth in the camera
axes those clients read (x forward, y left, z up)."""

from __future__ import annotations

import base64
import copy
import json
import math
import shutil
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import uvicorn
from fastapi.testclient import TestClient

from app.main import create_app
from app.settings import Settings
from app.usecases.gpp import GL_FROM_FLU
from services.geo.geodesy import Geodetic, ecef_from_enu_rotation, ecef_from_geodetic
from services.geo.geopose import CV_FROM_GL
from services.geometry.rigid import quaternion_to_matrix, rotation_error_deg
from services.localization.localizer import Localizer
from tests.api.test_geo import ENU_FROM_SCENE, ORIGIN, REGISTRATION_BODY, TRUTH
from tests.conftest import create_map, make_client, upload_view
from tools.synthetic.scene import SyntheticView, encode_jpeg

ORIGINS = "https://sparcl.example.org, http://localhost:5173"
PRIVACY = {
    "dataRetention": [],
    "dataAcceptableUse": [],
    "dataSanitizationApplied": [],
    "dataSanitizationRequested": [],
}


@pytest.fixture(scope="module")
def db_url(tmp_path_factory: pytest.TempPathFactory) -> str:
    return f"sqlite:///{tmp_path_factory.mktemp('gpp') / 'slloc.db'}"


@pytest.fixture(scope="module")
def served(
    db_url: str, localizer: Localizer, reference_views: list[SyntheticView]
) -> Iterator[tuple[TestClient, str]]:
    """A client with CORS on for two origins, and the scene's map with the true
    registration."""
    with make_client(db_url, localizer, cors_origins=ORIGINS) as client:
        map_id = create_map(client, "zurich")
        for view in reference_views:
            assert upload_view(client, map_id, view).status_code == 201  # type: ignore[attr-defined]
        response = client.put(f"/v1/maps/{map_id}/geo-registration", json=REGISTRATION_BODY)
        assert response.status_code == 200, response.text
        # the retrieval vocabulary the adds made due is trained in the background: every test
        # localizes against the map it leaves, not some before and some after it
        client.app.state.vocabulary_trainer.wait(120.0)  # type: ignore[attr-defined]
        yield client, map_id


def _fix(view: SyntheticView, east_m: float = 0.0) -> tuple[float, float, float]:
    """Latitude, longitude, height of the view's camera centre, moved ``east_m`` East."""
    enu = TRUTH.enu_from_map(view.cam_from_world.center[None])[0] + [east_m, 0.0, 0.0]
    lat, lon, h = TRUTH.geodetic_from_map(TRUTH.map_from_enu(enu[None]))[0]
    return float(lat), float(lon), float(h)


def _errors(geopose: dict, view: SyntheticView, axes: str = "flu") -> tuple[float, float]:  # type: ignore[type-arg]
    """Metres and degrees between an answer and the view's true GeoPose, its quaternion read
    in forward-left-up (``flu``) or OpenGL camera axes."""
    p = geopose["position"]
    got = ecef_from_geodetic(np.array([[p["lat"], p["lon"], p["h"]]]))[0]
    expected = ecef_from_geodetic(TRUTH.geodetic_from_map(view.cam_from_world.center[None]))[0]
    q = geopose["quaternion"]
    enu_from_cam = quaternion_to_matrix(np.array([q["w"], q["x"], q["y"], q["z"]]))
    ecef_from_cam = ecef_from_enu_rotation(Geodetic(p["lat"], p["lon"], p["h"])) @ enu_from_cam
    truth = (
        ecef_from_enu_rotation(ORIGIN)
        @ ENU_FROM_SCENE
        @ view.cam_from_world.rotation.T
        @ CV_FROM_GL
    )
    if axes == "flu":
        truth = truth @ GL_FROM_FLU
    return float(np.linalg.norm(got - expected)), rotation_error_deg(ecef_from_cam, truth)


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode()


def demo_client_v2(view: SyntheticView, east_m: float = 0.0) -> dict:  # type: ignore[type-arg]
    """As oscp-geopose-protocol's python/demo_client.py sends it: the JPEG file's bytes
    labelled RGBA32, the objects' ``__dict__`` as JSON (every default field, empty lists of
    the other readings), the GPS reading's accuracy left at its default 0.0."""
    lat, lon, h = _fix(view, east_m)
    cam = view.camera
    now = time.time() * 1000
    sensor = {
        "name": "",
        "model": "",
        "rigIdentifier": "",
        "rigRotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
        "rigTranslation": {"x": 0.0, "y": 0.0, "z": 0.0},
    }
    return {
        "type": "geopose",
        "id": "2f1c6f0e-3c39-4f59-9d63-1b0f4f0c6f11",
        "timestamp": now,
        "sensors": [
            {"type": "camera", "id": "my_camera_sensor", **sensor},
            {"type": "geolocation", "id": "my_gps_sensor", **sensor},
        ],
        "sensorReadings": {
            "cameraReadings": [
                {
                    "timestamp": now,
                    "sensorId": "my_camera_sensor",
                    "privacy": PRIVACY,
                    "sequenceNumber": 1,
                    "imageFormat": "RGBA32",
                    "size": [cam.width, cam.height],
                    "imageBytes": _b64(encode_jpeg(view.image)),
                    "imageOrientation": {"mirrored": False, "rotation": 0.0},
                    "params": {
                        "model": cam.model,
                        "modelParams": list(cam.params),
                        "minMaxDepth": [],
                        "minMaxDisparity": [],
                    },
                }
            ],
            "geolocationReadings": [
                {
                    "timestamp": now,
                    "sensorId": "my_gps_sensor",
                    "privacy": PRIVACY,
                    "latitude": lat,
                    "longitude": lon,
                    "altitude": h,
                    "accuracy": 0.0,
                    "altitudeAccuracy": 0.0,
                    "heading": 0.0,
                    "speed": 0.0,
                }
            ],
            "accelerometerReadings": [],
            "gyroscopeReadings": [],
            "magnetometerReadings": [],
            "wifiReadings": [],
            "bluetoothReadings": [],
        },
        "priorPoses": [],
    }


def demo_client_v1(view: SyntheticView, east_m: float = 0.0) -> dict:  # type: ignore[type-arg]
    """The same request in version 1's shape (protocolv1.md): ``sensorReadings`` a list of
    ``{timestamp, sensorId, privacy, reading}``, the intrinsics in the camera sensor's
    ``params``."""
    v2 = demo_client_v2(view, east_m)
    camera = dict(v2["sensorReadings"]["cameraReadings"][0])
    gps = dict(v2["sensorReadings"]["geolocationReadings"][0])
    params = camera.pop("params")
    readings = []
    for reading in (camera, gps):
        head = {k: reading.pop(k) for k in ("timestamp", "sensorId", "privacy")}
        readings.append({**head, "reading": reading})
    return {
        **{k: v2[k] for k in ("id", "timestamp", "type")},
        "sensors": [
            {"id": "my_camera_sensor", "type": "camera", "params": params},
            {"id": "my_gps_sensor", "type": "geolocation"},
        ],
        "sensorReadings": readings,
    }


def gpp_access(view: SyntheticView, east_m: float | None = 0.0) -> dict:  # type: ignore[type-arg]
    """As @oarc/gpp-access 0.2.1 serializes sparcl's request: ``geoLocationReadings`` with a
    capital L, a JPG, the heading NaN (null in JSON), sensors as {id, type}."""
    cam = view.camera
    now = int(time.time() * 1000)
    readings: dict[str, object] = {
        "cameraReadings": [
            {
                "sequenceNumber": 0,
                "imageFormat": "JPG",
                "size": [cam.width, cam.height],
                "imageBytes": _b64(encode_jpeg(view.image)),
                "imageOrientation": {"mirrored": False, "rotation": 0},
                "params": {"model": cam.model, "modelParams": list(cam.params)},
                "timestamp": now,
                "sensorId": "0",
                "privacy": PRIVACY,
            }
        ]
    }
    if east_m is not None:
        lat, lon, h = _fix(view, east_m)
        readings["geoLocationReadings"] = [
            {
                "latitude": lat,
                "longitude": lon,
                "altitude": h,
                "accuracy": 5,
                "altitudeAccuracy": 3,
                "heading": None,
                "speed": 0,
                "timestamp": now,
                "sensorId": "1",
                "privacy": PRIVACY,
            }
        ]
    return {
        "id": "9d3e8a55-4f0b-4b3c-8a8e-0c7f5b1f2a77",
        "timestamp": now,
        "type": "geopose",
        "sensors": [{"id": "0", "type": "camera"}, {"id": "1", "type": "geolocation"}],
        "sensorReadings": readings,
    }


def _post(client: TestClient, map_id: str, body: dict, **kwargs: object):  # type: ignore[no-untyped-def, type-arg]
    return client.post(f"/v1/maps/{map_id}/geopose", json=body, **kwargs)  # type: ignore[arg-type]


def _read_like_the_python_client(answer: dict) -> None:  # type: ignore[type-arg]
    """Every field GeoPoseResponse.fromJson reads is there."""
    assert answer["type"] == "geopose" and isinstance(answer["timestamp"], float)
    assert set(answer["accuracy"]) == {"position", "orientation"}
    assert set(answer["geopose"]["position"]) == {"lat", "lon", "h"}
    assert set(answer["geopose"]["quaternion"]) == {"x", "y", "z", "w"}


@pytest.mark.parametrize("shape", [demo_client_v2, demo_client_v1, gpp_access])
def test_published_clients_are_answered_within_2_cm(
    served: tuple[TestClient, str], query_views: list[SyntheticView], shape: object
) -> None:
    client, map_id = served
    view = query_views[1]
    body = shape(view)  # type: ignore[operator]
    response = _post(client, map_id, body)
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/json"
    answer = response.json()
    _read_like_the_python_client(answer)
    assert answer["id"] == body["id"]
    position, rotation = _errors(answer["geopose"], view)
    assert position < 0.02 and rotation < 0.5, (position, rotation)
    assert 0 < answer["accuracy"]["position"] < 0.05
    assert 0 < answer["accuracy"]["orientation"] < 1.0


def test_opengl_axes_on_request_and_the_120_degree_turn(
    served: tuple[TestClient, str], query_views: list[SyntheticView]
) -> None:
    client, map_id = served
    view = query_views[1]
    flu = _post(client, map_id, gpp_access(view)).json()["geopose"]
    gl = client.post(
        f"/v1/maps/{map_id}/geopose",
        params={"camera_axes": "opengl"},
        json=gpp_access(view),
    ).json()["geopose"]
    position, rotation = _errors(gl, view, axes="gl")
    assert position < 0.02 and rotation < 0.5, (position, rotation)

    def matrix(q: dict[str, float]) -> np.ndarray:  # type: ignore[type-arg]
        return quaternion_to_matrix(np.array([q["w"], q["x"], q["y"], q["z"]]))

    turn = rotation_error_deg(matrix(flu["quaternion"]), matrix(gl["quaternion"]))
    assert turn == pytest.approx(120.0, abs=0.5)
    assert (
        client.post(
            f"/v1/maps/{map_id}/geopose", params={"camera_axes": "ned"}, json=gpp_access(view)
        ).status_code
        == 422
    )


def test_worked_example_of_the_axes() -> None:
    """A level camera looking North, image top up: forward_left_up (0, 0, sin 45°, cos 45°),
    a 90° turn about Up from looking East; opengl (sin 45°, 0, 0, cos 45°)."""
    from services.geometry.rigid import matrix_to_quaternion

    enu_from_gl = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # x East, y Up, z South
    s = math.sqrt(0.5)
    np.testing.assert_allclose(matrix_to_quaternion(enu_from_gl), [s, s, 0, 0], atol=1e-12)
    np.testing.assert_allclose(
        matrix_to_quaternion(enu_from_gl @ GL_FROM_FLU), [s, 0, 0, s], atol=1e-12
    )


@pytest.mark.parametrize("spelling", ["geolocationReadings", "geoLocationReadings"])
def test_gps_hint_under_both_spellings(
    served: tuple[TestClient, str], query_views: list[SyntheticView], spelling: str
) -> None:
    """A fix 1 km East of the camera leaves no reference near it: not localized."""
    client, map_id = served
    view = query_views[2]
    for east_m, status in ((0.0, 200), (1000.0, 404)):
        body = gpp_access(view, east_m)
        body["sensorReadings"][spelling] = body["sensorReadings"].pop("geoLocationReadings")
        response = _post(client, map_id, body)
        assert response.status_code == status, (spelling, east_m, response.text)
    assert "no_references" in response.json()["detail"]
    far_demo = demo_client_v2(view, 1000.0)  # accuracy 0.0 (unknown) too
    assert _post(client, map_id, far_demo).status_code == 404


def test_prior_pose_narrows_retrieval_before_the_gps_fix(
    served: tuple[TestClient, str], query_views: list[SyntheticView]
) -> None:
    client, map_id = served
    view = query_views[3]
    first = _post(client, map_id, gpp_access(view, None))
    assert first.status_code == 200, first.text
    again = gpp_access(view, 1000.0)  # a bad fix, a good prior answer
    again["priorPoses"] = [first.json()]
    assert _post(client, map_id, again).status_code == 200
    far = copy.deepcopy(first.json())
    lat, lon, h = _fix(view, 1000.0)
    far["geopose"]["position"] = {"lat": lat, "lon": lon, "h": h}
    again = gpp_access(view, 0.0)
    again["priorPoses"] = [first.json(), far]  # the last one counts
    response = _post(client, map_id, again)
    assert response.status_code == 404 and "no_references" in response.json()["detail"]


def test_request_variants(served: tuple[TestClient, str], query_views: list[SyntheticView]) -> None:
    """Without ``size``, with two camera readings (the first localized), NaN and zero
    accuracies."""
    client, map_id = served
    view = query_views[1]
    body = gpp_access(view)
    camera = body["sensorReadings"]["cameraReadings"][0]
    del camera["size"]
    other = dict(camera, imageBytes=_b64(encode_jpeg(query_views[5].image)))
    body["sensorReadings"]["cameraReadings"].append(other)
    response = _post(client, map_id, body)
    assert response.status_code == 200, response.text
    assert _errors(response.json()["geopose"], view)[0] < 0.02
    text = json.dumps(demo_client_v2(view)).replace('"altitudeAccuracy": 0.0', '"a": NaN')
    text = text.replace('"accuracy": 0.0', '"accuracy": NaN')
    response = client.post(
        f"/v1/maps/{map_id}/geopose", content=text, headers={"content-type": "application/json"}
    )
    assert response.status_code == 200, response.text


@pytest.mark.parametrize(
    ("orientation", "status"),
    [
        ({"mirrored": False, "rotation": 360}, 200),
        ({"mirrored": True, "rotation": 0}, 422),
        ({"mirrored": False, "rotation": 90}, 422),
    ],
)
def test_image_orientation(
    served: tuple[TestClient, str],
    query_views: list[SyntheticView],
    orientation: dict[str, object],
    status: int,
) -> None:
    client, map_id = served
    body = gpp_access(query_views[1])
    body["sensorReadings"]["cameraReadings"][0]["imageOrientation"] = orientation
    response = _post(client, map_id, body)
    assert response.status_code == status, response.text
    if status == 422:
        assert "imageOrientation" in response.json()["detail"]


@pytest.mark.parametrize(
    ("accept", "status", "content_type"),
    [
        ("application/vnd.oscp+json; version=2.0", 200, "application/vnd.oscp+json; version=2.0"),
        ("application/vnd.oscp+json; version=1.0;", 200, "application/vnd.oscp+json; version=1.0"),
        ("application/vnd.oscp+json;version=2", 200, "application/vnd.oscp+json; version=2.0"),
        ("application/json", 200, "application/json"),
        ("*/*", 200, "application/json"),
        ("application/vnd.oscp+json; version=3.0", 406, "application/problem+json"),
        ("application/vnd.oscp+json; version=3.0, application/json;q=0.5", 200, None),
        ("text/html", 406, "application/problem+json"),
    ],
)
def test_accept_header_version(
    served: tuple[TestClient, str],
    query_views: list[SyntheticView],
    accept: str,
    status: int,
    content_type: str | None,
) -> None:
    client, map_id = served
    response = _post(client, map_id, gpp_access(query_views[1]), headers={"accept": accept})
    assert response.status_code == status, response.text
    if content_type is not None:
        assert response.headers["content-type"] == content_type
    if status == 200:
        _read_like_the_python_client(response.json())


def test_accuracy_is_the_mean_over_components(
    served: tuple[TestClient, str], query_views: list[SyntheticView]
) -> None:
    """/localize's 1-σ (horizontal = 2-D RMS, vertical, RMS rotation angle as yaw) against
    the protocol's means: (√2·horizontal + vertical) / 3 and yaw / √3."""
    client, map_id = served
    view = query_views[1]
    answer = _post(client, map_id, gpp_access(view, None)).json()["accuracy"]
    cam = view.camera
    response = client.post(
        f"/v1/maps/{map_id}/localize",
        files={"image": ("q.jpg", encode_jpeg(view.image), "image/jpeg")},
        data={
            "params": json.dumps(
                {
                    "camera": {
                        "model": cam.model,
                        "width": cam.width,
                        "height": cam.height,
                        "params": list(cam.params),
                    }
                }
            )
        },
    )
    sigma = response.json()["geopose_accuracy"]
    expected = (math.sqrt(2) * sigma["horizontal_m"] + sigma["vertical_m"]) / 3
    assert answer["position"] == pytest.approx(expected, rel=1e-6)
    assert answer["orientation"] == pytest.approx(sigma["yaw_deg"] / math.sqrt(3), rel=1e-6)


def test_cors_preflight_with_origins_configured(served: tuple[TestClient, str]) -> None:
    client, map_id = served
    preflight = {
        "origin": "https://sparcl.example.org",
        "access-control-request-method": "POST",
        "access-control-request-headers": "content-type, x-api-key",
    }
    response = client.options(f"/v1/maps/{map_id}/geopose", headers=preflight)
    assert response.status_code == 200, response.text
    assert response.headers["access-control-allow-origin"] == "https://sparcl.example.org"
    assert "POST" in response.headers["access-control-allow-methods"]
    assert "x-api-key" in response.headers["access-control-allow-headers"].lower()
    response = client.get("/v1/maps", headers={"origin": "http://localhost:5173"})
    assert response.headers["access-control-allow-origin"] == "http://localhost:5173"
    other = client.options(
        f"/v1/maps/{map_id}/geopose", headers={**preflight, "origin": "https://evil.example"}
    )
    assert other.status_code == 400
    assert "access-control-allow-origin" not in other.headers


def test_cors_is_off_without_origins(tmp_path: Path, localizer: Localizer) -> None:
    with make_client(f"sqlite:///{tmp_path / 'slloc.db'}", localizer) as client:
        response = client.options(
            "/v1/maps",
            headers={
                "origin": "https://sparcl.example.org",
                "access-control-request-method": "GET",
            },
        )
        assert response.status_code == 405
        assert "access-control-allow-origin" not in response.headers
        response = client.get("/v1/maps", headers={"origin": "https://sparcl.example.org"})
        assert "access-control-allow-origin" not in response.headers


# sparcl's request through @oarc/gpp-access 0.2.1 itself: its classes serialize the request,
# its sendRequest validates it (zod), posts it and validates the answer
GPP_ACCESS_SCRIPT = """
import { readFileSync } from 'node:fs';
import { CameraParam, GeoPoseRequest, IMAGEFORMAT, ImageOrientation, Privacy, SENSORTYPE,
         Sensor, sendRequest } from '@oarc/gpp-access';
const a = JSON.parse(readFileSync(process.argv[2], 'utf8'));
const request = new GeoPoseRequest('sparcl-1');
request.addSensor(new Sensor('0', SENSORTYPE.camera));
request.addSensor(new Sensor('1', SENSORTYPE.geolocation));
const params = new CameraParam();
params.model = a.model;
params.modelParams = a.params;
request.addCameraData(IMAGEFORMAT.JPG, [a.width, a.height], a.image, 0,
                      new ImageOrientation(false, 0), params, Date.now(), '0', new Privacy());
request.addGeoLocationData(a.lat, a.lon, a.h, 5, 3, 0, 0, Date.now(), '1', new Privacy());
console.log(JSON.stringify(await sendRequest(a.url, JSON.stringify(request))));
"""


@pytest.fixture(scope="module")
def gpp_access_script(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The script above bundled with @oarc/gpp-access 0.2.1 (npm, into a temporary folder:
    the package's ESM imports directories, which Node alone cannot load, so esbuild bundles
    it as sparcl's Vite does). Skipped without node and npm or without the registry."""
    npm, node = shutil.which("npm"), shutil.which("node")
    if npm is None or node is None:
        pytest.skip("node and npm are needed to run @oarc/gpp-access")
    root = tmp_path_factory.mktemp("gpp-access")
    install = [npm, "install", "--prefix", str(root), "--no-audit", "--no-fund"]
    install += ["--ignore-scripts", "@oarc/gpp-access@0.2.1", "esbuild@0.24.2"]
    try:
        done = subprocess.run(install, capture_output=True, text=True, timeout=300)
    except subprocess.TimeoutExpired:
        pytest.skip("npm install timed out (offline?)")
    if done.returncode != 0:
        pytest.skip(f"npm install failed (offline?): {done.stderr[-500:]}")
    (root / "client.mjs").write_text(GPP_ACCESS_SCRIPT)
    bundle = root / "client.bundle.mjs"
    subprocess.run(
        [
            str(root / "node_modules" / ".bin" / "esbuild"),
            str(root / "client.mjs"),
            "--bundle",
            "--platform=node",
            "--format=esm",
            f"--outfile={bundle}",
            "--log-level=warning",
        ],
        check=True,
        cwd=root,
        timeout=120,
    )
    return bundle


@pytest.fixture(scope="module")
def live_url(db_url: str, localizer: Localizer, served: tuple[TestClient, str]) -> Iterator[str]:
    """The service over HTTP (uvicorn in a thread) on the module's database."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    app = create_app(Settings(database_url=db_url), localizer=localizer)
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 60
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.05)
    yield f"http://127.0.0.1:{port}"
    server.should_exit = True
    thread.join(timeout=30)


def test_gpp_access_package_drives_the_endpoint(
    gpp_access_script: Path,
    live_url: str,
    served: tuple[TestClient, str],
    query_views: list[SyntheticView],
    tmp_path: Path,
) -> None:
    _, map_id = served
    view = query_views[4]
    lat, lon, h = _fix(view)
    cam = view.camera
    args = {
        "url": f"{live_url}/v1/maps/{map_id}/geopose",
        "image": _b64(encode_jpeg(view.image)),
        "width": cam.width,
        "height": cam.height,
        "model": cam.model,
        "params": list(cam.params),
        "lat": lat,
        "lon": lon,
        "h": h,
    }
    (tmp_path / "args.json").write_text(json.dumps(args))
    node = shutil.which("node")
    assert node is not None
    done = subprocess.run(
        [node, str(gpp_access_script), str(tmp_path / "args.json")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    answer = json.loads(done.stdout.strip().splitlines()[-1])
    assert answer["id"] == "sparcl-1"
    position, rotation = _errors(answer["geopose"], view)
    assert position < 0.02 and rotation < 0.5, (position, rotation)
