"""/localize as an AR app calls it: sensor intrinsics with a portrait upload, gravity, pose
conventions in the answer, and the requests refused with problem+json."""

from __future__ import annotations

import json

import numpy as np
import pytest
from fastapi.testclient import TestClient

from services.geometry.intrinsics_adaptation import rotated_from_camera
from services.geometry.pose_conventions import cam_from_world_of
from services.geometry.rigid import Rigid3d, pose_error
from tests.conftest import create_map, upload_view
from tools.synthetic.scene import SyntheticScene, SyntheticView, encode_jpeg, encode_png

PROBLEM = "application/problem+json"


def sensor_camera(view: SyntheticView, factor: int = 3) -> dict[str, object]:
    """The view's intrinsics as a phone gives them: for a landscape sensor image ``factor``
    times the upload's size."""
    return {
        "model": view.camera.model,
        "width": view.camera.width * factor,
        "height": view.camera.height * factor,
        "params": [p * factor for p in view.camera.params],
    }


def post(client: TestClient, map_id: str, image: bytes, params: dict[str, object]) -> object:
    return client.post(
        f"/v1/maps/{map_id}/localize",
        files={"image": ("q.jpg", image, "image/jpeg")},
        data={"params": json.dumps(params)},
    )


@pytest.fixture
def scene_map(client: TestClient, reference_views: list[SyntheticView]) -> str:
    map_id = create_map(client)
    for view in reference_views[:12]:
        assert upload_view(client, map_id, view).status_code == 201
    return map_id


def test_portrait_frame_with_sensor_intrinsics_gravity_and_conventions(
    client: TestClient, scene_map: str, scene: SyntheticScene, query_views: list[SyntheticView]
) -> None:
    view = query_views[0]
    portrait = np.ascontiguousarray(np.rot90(view.image, k=-1))
    turn = rotated_from_camera(90)
    truth = Rigid3d(turn @ view.cam_from_world.rotation, turn @ view.cam_from_world.translation)
    down = (view.cam_from_world.rotation @ [0.0, 1.0, 0.0]).tolist()  # sensor frame
    params = {
        "camera": sensor_camera(view),
        "gravity": {"down": down, "map_down": [0, 1, 0]},
        "output": {"frames": ["colmap", "opengl", "unity"]},
    }
    response = post(client, scene_map, encode_jpeg(portrait), params)
    assert response.status_code == 200, response.text  # type: ignore[attr-defined]
    result = response.json()  # type: ignore[attr-defined]
    assert result["localized"], result["reason"]
    adaptation = result["camera_adaptation"]
    assert adaptation["rotation_deg"] == 90 and adaptation["exif_orientation"] is None
    assert adaptation["scale"] == pytest.approx(1 / 3)
    assert adaptation["camera"]["width"] == 480 and adaptation["camera"]["height"] == 640
    assert result["upright_turn_deg"] == 270
    assert result["gravity_error_deg"] < 0.5
    pose = Rigid3d.from_quaternion(
        np.array(result["cam_from_world"]["rotation"]),
        np.array(result["cam_from_world"]["translation"]),
    )
    dt, dr = pose_error(pose, truth)
    assert dt < 0.01 * scene.extent and dr < 0.5
    for convention, answer in result["world_from_cam"].items():
        back = cam_from_world_of(np.array(answer["matrix"]), convention)
        assert pose_error(back, pose)[0] < 1e-9 and pose_error(back, pose)[1] < 1e-4
        np.testing.assert_allclose(answer["position"], np.array(answer["matrix"])[:3, 3])
        same = Rigid3d.from_quaternion(np.array(answer["rotation"]), np.zeros(3))
        np.testing.assert_allclose(same.rotation, np.array(answer["matrix"])[:3, :3], atol=1e-9)

    # the pose of the camera as the phone describes it (landscape sensor, ARKit's frame)
    params["output"] = {"frames": ["opengl"], "pose_of": "camera"}
    response = post(client, scene_map, encode_jpeg(portrait), params)
    opengl = response.json()["world_from_cam"]["opengl"]  # type: ignore[attr-defined]
    sensor_pose = cam_from_world_of(np.array(opengl["matrix"]), "opengl")
    dt, dr = pose_error(sensor_pose, view.cam_from_world)
    assert dt < 0.01 * scene.extent and dr < 0.5


def test_no_conventions_unless_asked(
    client: TestClient, scene_map: str, query_views: list[SyntheticView]
) -> None:
    response = post(client, scene_map, encode_png(query_views[0].image), {})
    result = response.json()  # type: ignore[attr-defined]
    assert result["localized"] and result["world_from_cam"] is None
    assert result["camera_adaptation"] is None


@pytest.mark.parametrize(
    ("image", "params", "fragment"),
    [
        ("landscape", {"camera": "sensor-800"}, "a camera of 640×480 or 480×640"),
        ("landscape", {"camera": "sensor", "camera_rotation_deg": 90}, "a camera of 480×640"),
        ("mirrored", {"camera": "sensor"}, "EXIF orientation 2 mirrors it"),
        ("landscape", {"gravity": {"down": [0, 0, 0]}}, "gravity: a direction must be"),
        (
            "landscape",
            {"gravity": {"down": [0, 1, 0], "map_down": [0, 0, 0]}},
            "gravity: a direction must be",
        ),
        ("landscape", {"camera_rotation_deg": 45}, "camera_rotation_deg"),
        ("landscape", {"output": {"frames": ["vulkan"]}}, "output.frames"),
    ],
)
def test_bad_ar_params_are_422(
    client: TestClient,
    query_views: list[SyntheticView],
    image: str,
    params: dict[str, object],
    fragment: str,
) -> None:
    map_id = create_map(client, "m")
    view = query_views[0]
    if params.get("camera") == "sensor":
        params["camera"] = sensor_camera(view)
    elif params.get("camera") == "sensor-800":
        params["camera"] = {
            "model": "PINHOLE",
            "width": 800,
            "height": 480,
            "params": [500, 500, 400, 240],
        }
    data = encode_jpeg(view.image, 2 if image == "mirrored" else None)
    response = post(client, map_id, data, params)
    assert response.status_code == 422  # type: ignore[attr-defined]
    assert response.headers["content-type"] == PROBLEM  # type: ignore[attr-defined]
    body = response.json()  # type: ignore[attr-defined]
    assert fragment in json.dumps(body, ensure_ascii=False), body
