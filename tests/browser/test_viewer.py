"""The map viewer in a real headless Chromium (the system's ``chromium`` package, driven by
playwright): a real uvicorn server on a free port with auth on and a map seeded from a
synthetic scene; the page is used as a person would (key, map, query upload) and what it draws
is checked in the DOM and in the pixels. Screenshots go to ``test-artifacts/`` (or
``$SLLOC_TEST_ARTIFACTS``)."""

from __future__ import annotations

import json
import os
import shutil
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
import uvicorn

from app.main import create_app
from app.settings import Settings
from app.viewer import vendor_installed
from services.localization.localizer import Localizer
from tests.conftest import image_metadata
from tools.synthetic.scene import SyntheticView, encode_png

playwright = pytest.importorskip("playwright.sync_api", reason="playwright is in the dev extra")

ROOT = Path(__file__).resolve().parents[2]
ARTIFACTS = Path(os.environ.get("SLLOC_TEST_ARTIFACTS", ROOT / "test-artifacts"))
ADMIN_KEY, CLIENT_KEY = "viewer-admin-key", "viewer-client-key"
NUM_REFERENCES = 12
QUERY_RGB = (0xE7, 0x4C, 0x3C)  # the query frustum's colour in viewer.js


def _chromium() -> str:
    path = os.environ.get("SLLOC_TEST_CHROMIUM") or shutil.which("chromium")
    if path is None:
        if os.environ.get("CI"):
            pytest.fail("chromium is missing in CI: scripts/test.sh installs it with apt-get")
        pytest.skip("chromium is not installed (apt-get install chromium; CI installs it)")
    if not vendor_installed():
        pytest.fail("three.js is not in app/web/vendor: run scripts/build_web.sh (needs npm)")
    return path


@dataclass(frozen=True)
class Served:
    url: str
    map_id: str
    query: SyntheticView
    query_png: Path


@pytest.fixture(scope="module")
def served(
    tmp_path_factory: pytest.TempPathFactory,
    localizer: Localizer,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> Iterator[Served]:
    tmp = tmp_path_factory.mktemp("viewer")
    settings = Settings(
        database_url=f"sqlite:///{tmp / 'viewer.db'}",
        api_keys=f"{ADMIN_KEY}:admin,{CLIENT_KEY}:client",
    )
    app = create_app(settings, localizer=localizer)
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    url = f"http://127.0.0.1:{sock.getsockname()[1]}"
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "the server did not start"
        time.sleep(0.05)
    try:
        with httpx.Client(base_url=url, headers={"X-API-Key": ADMIN_KEY}, timeout=60) as api:
            map_id = api.post("/v1/maps", json={"name": "synthetic room"}).json()["id"]
            for view in reference_views[:NUM_REFERENCES]:
                response = api.post(
                    f"/v1/maps/{map_id}/images",
                    files={"image": (view.name, encode_png(view.image), "image/png")},
                    data={"metadata": json.dumps(image_metadata(view))},
                )
                assert response.status_code == 201, response.text
        query = query_views[0]
        query_png = tmp / "query.png"
        query_png.write_bytes(encode_png(query.image))
        yield Served(url, map_id, query, query_png)
    finally:
        server.should_exit = True
        thread.join(timeout=30)


@pytest.fixture(scope="module")
def browser() -> Iterator[playwright.Browser]:
    executable = _chromium()
    with playwright.sync_playwright() as p:
        launched = p.chromium.launch(executable_path=executable, args=["--no-sandbox"])
        yield launched
        launched.close()


def _localize_in_page(page: playwright.Page, served: Served) -> dict[str, object]:
    """Type the client key, pick the map, upload the query and localize; returns the API's
    answer as the page received it."""
    page.goto(served.url + "/")
    page.wait_for_selector("body[data-ready=true]")
    page.fill("#api-key", CLIENT_KEY)
    page.click("#save-key")
    page.click(f"#maps button[data-map-id='{served.map_id}']")
    page.wait_for_selector("#localize:not([disabled])")
    page.set_input_files("#query-image", str(served.query_png))
    params = {"camera": image_metadata(served.query)["camera"], "top_k": 5}
    page.fill("#params", json.dumps(params))
    with page.expect_response(lambda r: r.url.endswith("/localize")) as answer:
        page.click("#localize")
    assert answer.value.status == 200
    result: dict[str, object] = answer.value.json()
    page.wait_for_selector("#matches[data-ready=true]")
    return result


def _pixels(png: bytes) -> np.ndarray:
    bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(int)


def test_viewer_localizes_and_draws(browser: playwright.Browser, served: Served) -> None:
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    page.goto(served.url + "/viewer/")
    page.wait_for_selector("body[data-ready=true]")
    # auth is on and the tab has no key yet: the map list is refused, and the page says so
    playwright.expect(page.locator("#status")).to_contain_text("HTTP 401")
    assert page.locator("#scene-note").inner_text() == ""  # three.js loaded

    result = _localize_in_page(page, served)
    assert result["localized"] is True

    scene = page.locator("#scene")
    assert scene.get_attribute("data-reference-frusta") == str(NUM_REFERENCES)
    assert scene.get_attribute("data-query-frustum") == "1"
    assert page.locator("#outcome").get_attribute("data-localized") == "true"
    # the page's own pose arithmetic (quaternion → R, centre −Rᵀt) agrees with the server's
    centre = json.loads(scene.get_attribute("data-query-centre") or "null")
    assert np.allclose(centre, result["camera_center"], atol=1e-9)
    assert page.locator("#num-inliers").inner_text() == str(result["num_inliers"])
    retrieved = result["retrieved"]
    inliers = result["inliers"]
    assert isinstance(retrieved, list) and isinstance(inliers, list) and inliers
    assert page.locator("li.retrieved").count() == len(retrieved)
    views = page.locator("canvas.match-view")
    assert views.count() == len(inliers)
    for i, pair in enumerate(inliers):
        assert views.nth(i).get_attribute("data-image-id") == pair["image_id"]
        assert views.nth(i).get_attribute("data-inliers") == str(len(pair["query_xy"]))

    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    shot = page.screenshot(path=ARTIFACTS / "viewer.png", full_page=True)
    assert shot[:8] == b"\x89PNG\r\n\x1a\n"
    # the 3D view drew the query frustum in its colour ...
    drawn = _pixels(scene.screenshot())
    query_pixels = np.all(np.abs(drawn - QUERY_RGB) < 40, axis=-1).sum()
    # (1-px lines: 43 on the first run, 0 with nothing drawn)
    assert query_pixels > 20, f"{query_pixels} pixels of the query frustum's colour"
    # ... and each match view holds the reference preview, not the grey stand-in
    match_view = _pixels(views.nth(0).screenshot())
    right = match_view[:, match_view.shape[1] // 2 + 20 :]
    assert right.std() > 20, "the reference half of the match view is blank"
    page.close()


def test_viewer_without_three_js_still_localizes(
    browser: playwright.Browser, served: Served
) -> None:
    page = browser.new_page(viewport={"width": 1200, "height": 900})
    page.route("**/viewer/vendor/**", lambda route: route.abort())  # as if never installed
    result = _localize_in_page(page, served)
    playwright.expect(page.locator("#scene-note")).to_contain_text("three.js is not installed")
    assert page.locator("#scene").get_attribute("data-reference-frusta") == "0"
    assert page.locator("#num-inliers").inner_text() == str(result["num_inliers"])
    assert page.locator("canvas.match-view").count() == len(result["inliers"] or [])  # type: ignore[arg-type]
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=ARTIFACTS / "viewer-without-three.png", full_page=True)
    page.close()
