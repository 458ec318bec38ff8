"""The AR client (``/ar``) in a real headless Chromium (the system's ``chromium``, driven by
playwright) whose fake camera plays real redkitchen frames: a ``slloc serve`` subprocess with
auth on and a map of redkitchen references, the page opened with the map, the client key and a
1 s cadence in its query string. Every answer the page records (``window.arLog``) is matched
to the frame it localized, which is identified from the thumbnail the page keeps of it (the
played frame it correlates best with), and compared with that frame's ground truth
(``poses_c2w_sfm.csv``). The overlay's projection is checked against the pose's own
projection. The screenshot goes to the test's ``tmp_path`` (its path is printed).

The dataset is ``../shared/datasets/redkitchen`` beside the repository (its licence keeps it
out of the repository); without it the test is skipped."""

from __future__ import annotations

import base64
import os
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from app.schemas.geometry import PoseSchema
from app.viewer import vendor_installed
from services.geometry.rigid import pose_error
from services.types import FloatArray
from tools.evaluation.datasets import PosedImage, redkitchen_dataset
from tools.evaluation.runner import HttpRunner
from tools.evaluation.server import LocalServer

playwright = pytest.importorskip("playwright.sync_api", reason="playwright is in the dev extra")

ROOT = Path(__file__).resolve().parents[2]
ADMIN_KEY, CLIENT_KEY = "ar-admin-key", "ar-client-key"
REFERENCES = slice(0, 500, 10)  # the dataset's reference range, every 10th frame: 50 images
QUERIES = slice(510, 1000, 30)  # its query range, every 30th frame: 17 frames
FPS = 2  # of the fake camera's video
HOLD = 3  # video frames per query frame: each is shown 1.5 s, the page localizes every 1 s
MAX_M, MAX_DEG = 0.10, 5.0
MIN_WITHIN = 0.8  # of the answers
MIN_FRAMES = 10  # distinct query frames localized by the page
# size at which uploads are matched to the played frames: an upload correlates > 0.998 with its
# frame, the played frames at most 0.76 with each other
THUMB = (80, 60)


def _chromium() -> str:
    path = os.environ.get("SLLOC_TEST_CHROMIUM") or shutil.which("chromium")
    if path is None:
        if os.environ.get("CI"):
            pytest.fail("chromium is missing in CI: scripts/test.sh installs it with apt-get")
        pytest.skip("chromium is not installed (apt-get install chromium; CI installs it)")
    if not vendor_installed():
        pytest.fail("three.js is not in app/web/vendor: run scripts/build_web.sh (needs npm)")
    return path


def _redkitchen() -> Path:
    root = (ROOT.parent / "shared" / "datasets" / "redkitchen").resolve()
    if not (root / "poses_c2w_sfm.csv").is_file():
        pytest.skip(f"no redkitchen dataset at {root} (its licence keeps it out of the repository)")
    return root


def write_y4m(path: Path, frames: list[np.ndarray], fps: int, hold: int) -> None:
    """A YUV4MPEG2 video (4:2:0, ``C420jpeg``) of BGR ``frames`` (each H×W×3 uint8, W and H
    even), each repeated ``hold`` times at ``fps`` frames per second."""
    height, width = frames[0].shape[:2]
    with path.open("wb") as f:
        f.write(f"YUV4MPEG2 W{width} H{height} F{fps}:1 Ip A1:1 C420jpeg\n".encode())
        for frame in frames:
            planes = cv2.cvtColor(frame, cv2.COLOR_BGR2YUV_I420).tobytes()  # Y, U, V planes
            for _ in range(hold):
                f.write(b"FRAME\n")
                f.write(planes)


def _thumbnail(bgr: np.ndarray) -> FloatArray:
    """Zero-mean, unit-norm grey thumbnail: the dot product of two is their correlation."""
    grey = cv2.resize(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), THUMB, interpolation=cv2.INTER_AREA)
    values = grey.astype(np.float64).ravel()
    values -= values.mean()
    return values / np.linalg.norm(values)


def _decode_data_url(url: str, flags: int) -> np.ndarray:
    assert url.startswith("data:image/"), url[:40]
    data = base64.b64decode(url.split(",", 1)[1])
    return cv2.imdecode(np.frombuffer(data, np.uint8), flags)


@dataclass(frozen=True)
class Served:
    url: str
    map_id: str
    queries: list[PosedImage]
    video: Path


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    dataset = redkitchen_dataset(_redkitchen())
    references = dataset.images[REFERENCES]
    queries = dataset.images[QUERIES]
    video = tmp_path_factory.mktemp("ar") / "redkitchen-queries.y4m"
    write_y4m(video, [cv2.imread(str(q.image_path)) for q in queries], FPS, HOLD)
    env = {"SLLOC_API_KEYS": f"{ADMIN_KEY}:admin,{CLIENT_KEY}:client"}
    with LocalServer(env) as server:
        runner = HttpRunner(server.url, ADMIN_KEY, map_name="redkitchen-ar", keep_map=True)
        for image in references:
            runner.add_reference(image, None)
        runner.index_references(len(references))
        yield Served(server.url, runner.map_id, queries, video)
        runner.close()


@pytest.fixture(scope="module")
def browser(served: Served) -> Iterator[playwright.Browser]:
    executable = _chromium()
    args = [
        "--no-sandbox",
        "--use-fake-device-for-media-stream",
        "--use-fake-ui-for-media-stream",
        f"--use-file-for-fake-video-capture={served.video}",
    ]
    with playwright.sync_playwright() as p:
        launched = p.chromium.launch(executable_path=executable, args=args)
        yield launched
        launched.close()


def _wait_idle(page: playwright.Page) -> None:
    page.wait_for_function("document.getElementById('outcome').dataset.state !== 'busy'")


def test_ar_client_localizes_the_camera(
    browser: playwright.Browser, served: Served, tmp_path: Path
) -> None:
    thumbnails = np.stack([_thumbnail(cv2.imread(str(q.image_path))) for q in served.queries])
    context = browser.new_context(viewport={"width": 1000, "height": 900})
    context.grant_permissions(["camera"], origin=served.url)
    page = context.new_page()
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))

    page.goto(f"{served.url}/ar/?map={served.map_id}&key={CLIENT_KEY}&interval=1")
    page.wait_for_selector("body[data-ready=true]")
    assert "key=" not in page.url  # the key went to sessionStorage, not the history
    assert page.locator("#video").get_attribute("data-size") == "640x480"
    assert page.locator("#map").input_value() == served.map_id
    assert page.locator("#overlay").get_attribute("data-frusta") == "50"
    assert page.locator("#overlay-note").inner_text() == ""  # three.js loaded

    # the sequence once through, at the page's own cadence
    page.wait_for_function("window.arLog.length >= 1", timeout=30_000)
    page.wait_for_timeout(1000 * len(served.queries) * HOLD / FPS)
    page.uncheck("#auto")
    _wait_idle(page)
    log: list[dict[str, Any]] = page.evaluate("window.arLog")

    within = 0
    seen: set[int] = set()
    matched: list[float] = []  # each upload's correlation with the frame it is taken for
    lines = []
    for entry in log:
        assert entry["http_status"] == 200 and entry["error"] is None, entry
        assert entry["camera"]["params"] == [525.0, 525.0, 320.0, 240.0]  # the references'
        # the frame the page localized: its thumbnail in the log against the played frames
        shown = _decode_data_url(entry["frame"], cv2.IMREAD_COLOR)
        correlation = thumbnails @ _thumbnail(shown)
        index = int(np.argmax(correlation))
        assert correlation[index] > 0.97, f"upload {entry['seq']} matches no played frame"
        matched.append(float(correlation[index]))
        seen.add(index)
        truth = served.queries[index]
        if entry["localized"]:
            pose = PoseSchema.model_validate(entry["cam_from_world"]).to_rigid()
            error_m, error_deg = pose_error(pose, truth.cam_from_world)
            ok = error_m <= MAX_M and error_deg <= MAX_DEG
            within += ok
            lines.append(
                f"{truth.name}: {100 * error_m:.1f} cm {error_deg:.2f}° "
                f"confidence {entry['confidence']:.2f}"
            )
        else:
            lines.append(f"{truth.name}: not localized ({entry['reason']})")
    print("\n".join(lines))
    print(
        f"{within}/{len(log)} answers within ({100 * MAX_M:.0f} cm, {MAX_DEG:.0f}°), "
        f"{len(seen)}/{len(served.queries)} frames shown, median round trip "
        f"{np.median([e['latency_ms'] for e in log]):.0f} ms; uploads matched to played "
        f"frames with correlation >= {min(matched):.4f}"
    )
    assert len(seen) >= MIN_FRAMES, f"only {len(seen)} distinct frames were localized"
    assert within >= MIN_WITHIN * len(log), f"{within}/{len(log)} within tolerance"

    # on demand: the button localizes the frame shown now; the overlay draws the references
    # with the page's projection, which agrees with the pose's own
    for _ in range(3):
        count = len(log)
        page.click("#localize-now")
        page.wait_for_function(f"window.arLog.length > {count}")
        log = page.evaluate("window.arLog")
        if log[-1]["localized"]:
            break
    entry = log[-1]
    assert entry["trigger"] == "button" and entry["localized"], entry
    _check_overlay(page, entry)
    playwright.expect(page.locator("#outcome")).to_contain_text("Localized, confidence")
    shot = tmp_path / "ar-client.png"
    page.screenshot(path=shot, full_page=True)
    print(f"screenshot: {shot}")

    assert not errors, errors

    # an answer without a pose (here the service's own answer, its pose taken out) is shown as
    # not localized, with its reason, and the overlay is hidden
    def without_pose(route: playwright.Route) -> None:
        answer = route.fetch().json()
        # as the API answers it: the candidate is the pose, `confidence` is the candidate's
        candidate = answer["cam_from_world"]
        answer.update(localized=False, reason="low_confidence", candidate=candidate)
        answer.update(confidence=0.05, cam_from_world=None, camera_center=None, world_from_cam=None)
        route.fulfill(json=answer)

    page.route("**/localize", without_pose)
    page.click("#localize-now")
    playwright.expect(page.locator("#outcome")).to_contain_text(
        "Not localized: low_confidence (a candidate pose had confidence 0.05)"
    )
    assert page.locator("#outcome").get_attribute("data-state") == "failed"
    assert page.locator("#overlay").get_attribute("data-shown") == "false"
    page.unroute("**/localize")

    # a refused request is shown as failed, with the service's reason
    page.select_option("#intrinsics", "focal")
    page.fill("#focal", "5")
    page.click("#localize-now")
    playwright.expect(page.locator("#outcome")).to_contain_text("Failed: HTTP 422")
    assert page.locator("#outcome").get_attribute("data-state") == "failed"
    assert page.locator("#overlay").get_attribute("data-shown") == "false"
    assert errors == [
        "Failed to load resource: the server responded with a status of 422 (Unprocessable Entity)"
    ], errors
    context.close()


def _check_overlay(page: playwright.Page, entry: dict[str, Any]) -> None:
    assert page.locator("#overlay").get_attribute("data-shown") == "true"
    pose = PoseSchema.model_validate(entry["cam_from_world"]).to_rigid()
    fx, fy, cx, cy = entry["camera"]["params"]
    # points 1-3 m in front of the camera, across the image
    pixels = np.array([[100.0, 80.0], [320.0, 240.0], [600.0, 400.0]])
    depths = np.array([1.0, 2.0, 3.0])
    in_camera = np.column_stack(
        [(pixels[:, 0] - cx) / fx * depths, (pixels[:, 1] - cy) / fy * depths, depths]
    )
    in_world = (in_camera - pose.translation) @ pose.rotation  # Rᵀ (x − t), row-wise
    for point, pixel in zip(in_world, pixels, strict=True):
        u, v, _ = page.evaluate("p => window.arOverlay.project(p)", point.tolist())
        assert abs(u - pixel[0]) < 1e-3 and abs(v - pixel[1]) < 1e-3, (u, v, pixel)
    # the frusta were drawn: the overlay's canvas is not empty
    data_url = page.evaluate("document.querySelector('#overlay canvas').toDataURL('image/png')")
    rgba = _decode_data_url(data_url, cv2.IMREAD_UNCHANGED)
    drawn = int((rgba[..., 3] > 0).sum())
    assert drawn > 200, f"{drawn} overlay pixels drawn"
