"""Capture sessions extend a map: frames with poses in the device's own frame are aligned to
the map and added, refused with the reason (adding nothing), or start an empty map; their
frames flag the references that no longer match the place. SQLite and
PostgreSQL, real SIFT on rendered views whose poses are exact, sessions expressed in frames
that the test moves, turns and scales."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from services.geo.geodesy import Geodetic, ecef_from_geodetic, geodetic_from_enu
from services.geo.registration import GeoRegistration
from services.geometry.rigid import Rigid3d, quaternion_to_matrix, rotation_error_deg
from tests.conftest import localize_view, make_client, seen_elsewhere, upload_view
from tests.polling import wait_until
from tools.synthetic.scene import SyntheticScene, SyntheticView, encode_png

# the session's frame in the map's: turned 40° about an oblique axis and moved
TURN = quaternion_to_matrix(np.array([np.cos(0.35), 0.3, np.sin(0.35) * 0.8, 0.2]))
WORLD_FROM_SESSION = Rigid3d(TURN, np.array([1.5, -0.4, 2.0]))
# where the session's frame lies on the globe: East-North-Up at ORIGIN from the session's
# frame (its y axis down, its z axis turned 30° from North) and moved
ORIGIN = Geodetic(47.3769, 8.5417, 408.0)
_YAW = np.radians(30.0)
ENU_FROM_SESSION = Rigid3d(
    np.array([[np.cos(_YAW), -np.sin(_YAW), 0], [np.sin(_YAW), np.cos(_YAW), 0], [0, 0, 1]])
    @ np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
    np.array([12.0, -7.0, 1.5]),
)


@pytest.fixture
def client(database_url: str, localizer: Any, tmp_path: Path) -> Any:
    with make_client(database_url, localizer, data_dir=tmp_path / "data") as c:
        yield c


def _session_pose(view: SyntheticView, scale: float = 1.0) -> dict[str, object]:
    """The view's ``cam_from_session`` for a session whose frame is ``WORLD_FROM_SESSION``
    and whose unit is ``scale`` metres."""
    cam_from_session = view.cam_from_world.compose(WORLD_FROM_SESSION)
    return {
        "rotation": [float(v) for v in cam_from_session.quaternion],
        "translation": [float(v) / scale for v in cam_from_session.translation],
    }


def _center(view: SyntheticView) -> Any:
    """The view's camera centre in the session's frame."""
    return view.cam_from_world.compose(WORLD_FROM_SESSION).center


def _gps(view: SyntheticView) -> dict[str, float]:
    """The exact GPS fix of the view's camera centre (``ENU_FROM_SESSION``)."""
    enu = ENU_FROM_SESSION.rotation @ _center(view) + ENU_FROM_SESSION.translation
    latitude, longitude, height = geodetic_from_enu(enu[None], ORIGIN)[0]
    return {"latitude": latitude, "longitude": longitude, "height": height, "accuracy_m": 0.05}


def _map(client: TestClient, views: list[SyntheticView]) -> str:
    created = client.post("/v1/maps", json={"name": "scene", "features": {"preset": "sift"}})
    assert created.status_code == 201, created.text
    map_id = str(created.json()["id"])
    for view in views:
        assert upload_view(client, map_id, view).status_code == 201
    return map_id


def _frame(
    client: TestClient,
    map_id: str,
    session_id: str,
    view: SyntheticView,
    width: int | None = None,
    gps: object = None,
    **pose: object,
) -> Any:
    camera = view.camera
    metadata = {
        "name": view.name,
        "camera": {
            "model": camera.model,
            "width": width or camera.width,
            "height": camera.height,
            "params": list(camera.params),
        },
        **(pose or {"cam_from_session": _session_pose(view)}),
        **({"gps": gps} if gps is not None else {}),
    }
    return client.post(
        f"/v1/maps/{map_id}/sessions/{session_id}/frames",
        files={"image": (view.name, encode_png(view.image), "image/png")},
        data={"metadata": json.dumps(metadata)},
    )


def _capture(
    client: TestClient,
    map_id: str,
    views: list[SyntheticView],
    metric: bool = True,
    scale: float = 1.0,
    name: str = "walk",
    keep_all: bool = True,
    gps: bool = False,
) -> dict[str, Any]:
    """Uploads the views as a session (with ``gps``, each frame with its exact GPS fix),
    submits it and returns it once decided."""
    body = {"name": name, "metric": metric, "keep_all": keep_all}
    created = client.post(f"/v1/maps/{map_id}/sessions", json=body)
    assert created.status_code == 201, created.text
    session_id = created.json()["id"]
    assert created.headers["location"] == f"/v1/maps/{map_id}/sessions/{session_id}"
    for view in views:
        fix = _gps(view) if gps else None
        response = _frame(
            client, map_id, session_id, view, gps=fix, cam_from_session=_session_pose(view, scale)
        )
        assert response.status_code == 201, response.text
        assert response.json()["gps"] == fix
    submitted = client.post(f"/v1/maps/{map_id}/sessions/{session_id}/submit")
    assert submitted.status_code == 202, submitted.text
    assert submitted.json()["state"] == "queued" and submitted.json()["frames"] == len(views)

    def decided() -> bool:
        client.app.state.capture_runner.worker.wait(120.0)  # type: ignore[attr-defined]
        state = client.get(f"/v1/maps/{map_id}/sessions/{session_id}").json()["state"]
        return state in ("added", "refused", "failed")

    assert wait_until(decided, timeout_s=240.0)
    answer: dict[str, Any] = client.get(f"/v1/maps/{map_id}/sessions/{session_id}").json()
    return answer


def _images(client: TestClient, map_id: str) -> dict[str, dict[str, Any]]:
    items = client.get(f"/v1/maps/{map_id}/images", params={"limit": 1000}).json()["items"]
    return {item["name"]: item for item in items}


def _pose_errors(
    image: dict[str, Any], view: SyntheticView, world_from_map: Rigid3d
) -> tuple[float, float]:
    pose = image["cam_from_world"]
    cam_from_map = Rigid3d.from_quaternion(
        np.array(pose["rotation"]), np.array(pose["translation"])
    )
    truth = view.cam_from_world.compose(world_from_map)
    return (
        float(np.linalg.norm(cam_from_map.center - truth.center)),
        rotation_error_deg(cam_from_map.rotation, truth.rotation),
    )


@pytest.mark.parametrize("metric", [True, False])
def test_a_session_is_aligned_and_its_frames_added(
    client: TestClient,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
    metric: bool,
) -> None:
    map_id = _map(client, reference_views[:12])
    session_views = query_views[:8]
    # a metric session, or one in a unit of half a metre whose scale is estimated
    scale = 1.0 if metric else 0.5
    session = _capture(client, map_id, session_views, metric=metric, scale=scale, gps=True)
    assert session["state"] == "added", session
    alignment = session["alignment"]
    assert alignment["mode"] == "aligned" and alignment["reason"] is None
    # its frames' GPS goes onto the references; only a bootstrap geo-registers the map
    assert alignment["geo_registration"] is None
    assert client.get(f"/v1/maps/{map_id}/geo-registration").status_code == 404
    assert alignment["agreeing"] >= 3 and alignment["added"] == len(session_views)
    assert alignment["map_from_session"]["scale"] == pytest.approx(scale, rel=0.01)
    assert alignment["rms_position_m"] < 0.02
    # exact session poses: the frames that anchor the drift correction barely move
    assert alignment["drift_correction_m"]["max"] < 0.02
    assert (
        alignment["skipped"] == 0
    )  # keep_all    assert len(alignment["checked"]) == len(session_views)
    assert session["progress"] == {"done": 2 * len(session_views), "total": 2 * len(session_views)}
    images = _images(client, map_id)
    assert len(images) == 12 + len(session_views)
    for view in session_views:
        image = images[f"walk/{view.name}"]
        position, rotation = _pose_errors(image, view, Rigid3d.identity())
        assert position < 0.02 and rotation < 0.5, (view.name, position, rotation)
        assert image["has_original"] and image["gps"] == _gps(view)
        original = client.get(f"/v1/maps/{map_id}/images/{image['id']}/original")
        assert original.content == encode_png(view.image)
    # the frames serve as references: a query localizes against the grown map
    answer = localize_view(client, map_id, query_views[9]).json()
    assert answer["localized"], answer
    assert 'slloc_capture_sessions_total{state="added"} 1.0' in client.get("/metrics").text


def test_a_session_adds_only_the_frames_that_add_a_view(
    client: TestClient, reference_views: list[SyntheticView]
) -> None:
    map_id = _map(client, reference_views[:12])
    # four of the map's own views again, and two views it lacks
    again = [*reference_views[:4], *reference_views[12:14]]
    session = _capture(client, map_id, again, keep_all=False)
    assert session["state"] == "added", session
    alignment = session["alignment"]
    assert alignment["skipped"] == 4 and alignment["added"] == 2
    assert alignment["spacing_m"] > 0.1
    assert session["progress"]["done"] == session["progress"]["total"]
    names = set(_images(client, map_id))
    assert {f"walk/{v.name}" for v in reference_views[12:14]} <= names
    assert not any(f"walk/{v.name}" in names for v in reference_views[:4])
    # the skipped frames' blobs are gone with them
    blobs = client.app.state.blobs  # type: ignore[attr-defined]
    assert sum(1 for _ in blobs.list("originals/")) == 14


def test_a_session_that_does_not_fit_is_refused_and_adds_nothing(
    client: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    map_id = _map(client, reference_views[:12])
    # said to be metric while its unit is a third of a metre: no rigid transform fits it
    session = _capture(client, map_id, query_views[:8], metric=True, scale=1 / 3)
    assert session["state"] == "refused", session
    alignment = session["alignment"]
    assert alignment["map_from_session"] is None
    assert "disagree" in alignment["reason"] and "not in metres" in alignment["reason"]
    assert any(not row["agrees"] for row in alignment["checked"])
    assert len(_images(client, map_id)) == 12
    # its frames' blobs are gone: only the references' remain
    blobs = client.app.state.blobs  # type: ignore[attr-defined]
    assert sum(1 for _ in blobs.list("originals/")) == 12


def test_an_empty_map_is_bootstrapped_from_one_session(
    client: TestClient, reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> None:
    created = client.post("/v1/maps", json={"name": "new", "features": {"preset": "sift"}})
    map_id = created.json()["id"]
    session = _capture(client, map_id, reference_views[:12])
    assert session["state"] == "added", session
    assert session["alignment"]["mode"] == "bootstrap"
    assert session["alignment"]["map_from_session"]["matrix"] == np.eye(4).tolist()
    # frames without GPS (nor EXIF): the map stays off the globe
    assert session["alignment"]["geo_registration"] == {
        "set": False,
        "reason": "fewer than 3 frames carry GPS with height",
        "num_references": None,
        "num_inliers": None,
        "residual_rms_m": None,
    }
    assert client.get(f"/v1/maps/{map_id}/geo-registration").status_code == 404
    images = _images(client, map_id)
    assert len(images) == 12
    # the map's frame is the session's: a query localizes where the session would put it
    view = query_views[0]
    answer = localize_view(client, map_id, view).json()
    assert answer["localized"], answer
    truth = view.cam_from_world.compose(WORLD_FROM_SESSION)
    assert np.linalg.norm(np.array(answer["camera_center"]) - truth.center) < 0.05


def test_a_session_that_bootstraps_a_map_geo_registers_it_from_its_frames_gps(
    client: TestClient, reference_views: list[SyntheticView]
) -> None:
    created = client.post("/v1/maps", json={"name": "new", "features": {"preset": "sift"}})
    map_id = created.json()["id"]
    views = reference_views[:8]
    session = _capture(client, map_id, views, gps=True)
    assert session["state"] == "added", session
    geo = session["alignment"]["geo_registration"]
    assert geo["set"] is True and geo["reason"] is None, geo
    assert geo["num_references"] == geo["num_inliers"] == len(views)
    assert geo["residual_rms_m"] < 0.01
    response = client.get(f"/v1/maps/{map_id}/geo-registration")
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["source"] == "estimated" and body["num_inliers"] == len(views)
    assert body["scale"] == pytest.approx(1.0, abs=1e-3)
    origin = body["origin"]
    registration = GeoRegistration.from_quaternion(
        Geodetic(origin["latitude"], origin["longitude"], origin["height"]),
        np.array(body["enu_from_map"]["rotation"]),
        np.array(body["enu_from_map"]["translation"]),
        body["scale"],
    )
    # each frame's centre in the map (the session's frame) lands on its GPS position
    for view in views:
        fix = _gps(view)
        truth = ecef_from_geodetic(np.array([[fix["latitude"], fix["longitude"], fix["height"]]]))
        placed = ecef_from_geodetic(registration.geodetic_from_map(_center(view)[None]))
        assert np.linalg.norm(placed - truth) < 0.03, view.name


def test_session_requests_are_checked(
    client: TestClient, reference_views: list[SyntheticView]
) -> None:
    created = client.post("/v1/maps", json={"name": "m", "features": {"preset": "sift"}})
    map_id = created.json()["id"]
    base = f"/v1/maps/{map_id}/sessions"
    # a session of unknown scale cannot define an empty map's frame
    unknown = client.post(base, json={"name": "loose", "metric": False}).json()["id"]
    assert _frame(client, map_id, unknown, reference_views[0]).status_code == 201
    refused = client.post(f"{base}/{unknown}/submit")
    assert refused.status_code == 422 and "unknown scale" in refused.json()["detail"]
    # names are unique in the map; an empty session cannot be submitted
    session_id = client.post(base, json={"name": "walk"}).json()["id"]
    assert client.post(base, json={"name": "walk"}).status_code == 409
    empty = client.post(f"{base}/{session_id}/submit")
    assert empty.status_code == 409 and "no frame" in empty.json()["detail"]
    # one pose per frame, in one of the two forms
    both = _frame(
        client,
        map_id,
        session_id,
        reference_views[0],
        cam_from_session=_session_pose(reference_views[0]),
        session_pose={"position": [0, 0, 0], "orientation": [1, 0, 0, 0]},
    )
    assert both.status_code == 422 and "either session_pose or cam_from_session" in both.text
    # the camera must fit the image
    view = reference_views[0]
    wrong = _frame(client, map_id, session_id, view, width=view.camera.width + 2)
    assert wrong.status_code == 422 and "camera is" in wrong.json()["detail"]
    # a GPS fix must be one
    off = _frame(client, map_id, session_id, view, gps={"latitude": 91.0, "longitude": 8.5})
    assert off.status_code == 422 and "latitude" in off.text
    assert client.get(f"{base}/{session_id}").json()["frames"] == 0
    # an AR session pose (ARKit's camera.transform) is taken as the localize endpoint takes it
    ar = _frame(
        client,
        map_id,
        session_id,
        reference_views[1],
        session_pose={"position": [0.1, 0.2, 0.3], "orientation": [1, 0, 0, 0]},
    )
    assert ar.status_code == 201, ar.text
    assert _frame(client, map_id, session_id, reference_views[1]).status_code == 409  # name
    assert client.post(f"{base}/{session_id}/submit").status_code == 202
    late = _frame(client, map_id, session_id, reference_views[2])
    assert late.status_code == 409 and "takes no more frames" in late.json()["detail"]
    unknown_session = client.get(f"{base}/00000000-0000-0000-0000-000000000000")
    assert unknown_session.status_code == 404
    # deleting the open session removes its waiting frame's blobs
    assert client.delete(f"{base}/{unknown}").status_code == 204
    assert client.get(f"{base}/{unknown}").status_code == 404
    listed = client.get(base).json()
    assert listed["total"] == 1 and listed["items"][0]["name"] == "walk"


def test_a_reference_whose_image_shows_another_place_is_flagged_stale(
    client: TestClient, scene: SyntheticScene, reference_views: list[SyntheticView]
) -> None:
    views = reference_views[:12]
    swapped = views[3]
    map_id = _map(client, [v for v in views if v is not swapped])
    assert upload_view(client, map_id, seen_elsewhere(swapped)).status_code == 201
    # the place as it is now: each reference's view again, from 5 cm to its right
    frames = []
    for view in views:
        moved = Rigid3d(
            view.cam_from_world.rotation, view.cam_from_world.translation - [0.05, 0, 0]
        )
        rendered, _ = scene.render(moved)
        frames.append(SyntheticView(f"now-{view.name}", view.camera, moved, rendered, None))
    session = _capture(client, map_id, frames, keep_all=False)
    assert session["state"] == "added", session
    assert [s["name"] for s in session["alignment"]["stale"]] == [swapped.name]
    flagged = client.get(f"/v1/maps/{map_id}/images", params={"stale": True}).json()
    assert [item["name"] for item in flagged["items"]] == [swapped.name]
    assert "capture session 'walk'" in flagged["items"][0]["stale"]["reason"]
    others = client.get(f"/v1/maps/{map_id}/images", params={"stale": False}).json()
    assert others["total"] == len(_images(client, map_id)) - 1
    assert all(item["stale"] is None for item in others["items"])
    # a map that retires its stale references deletes them at once
    patched = client.patch(f"/v1/maps/{map_id}", json={"retire_stale": True})
    assert patched.status_code == 200 and patched.json()["retire_stale"] is True
    again = _capture(client, map_id, frames, keep_all=False, name="again")
    [retired] = again["alignment"]["stale"]
    assert retired["name"] == swapped.name and retired["retired"] is True
    assert swapped.name not in _images(client, map_id)
