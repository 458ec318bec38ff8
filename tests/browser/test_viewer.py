"""The map viewer in a real headless Chromium (the system's ``chromium`` package, driven by
playwright): a real uvicorn server on a free port with auth on and a map seeded from a
synthetic scene; the page is used as a person would (key, map, query upload) and what it draws
is checked in the DOM, in the page's state (data attributes) and in the pixels, with no
JavaScript error on the way. Screenshots go to pytest's ``tmp_path`` (their paths printed) and
to ``test-artifacts/`` (or ``$SLLOC_TEST_ARTIFACTS``). The server runs sift only (no exported
model), as the self-evaluation tests' does."""

from __future__ import annotations

import json
import os
import shutil
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

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
from tests.polling import wait_until
from tools.synthetic.scene import SyntheticView, encode_png

playwright = pytest.importorskip("playwright.sync_api", reason="playwright is in the dev extra")

ROOT = Path(__file__).resolve().parents[2]
ARTIFACTS = Path(os.environ.get("SLLOC_TEST_ARTIFACTS", ROOT / "test-artifacts"))
ADMIN_KEY, CLIENT_KEY = "viewer-admin-key", "viewer-client-key"
NUM_REFERENCES = 12
QUERY_RGB = (0xE7, 0x4C, 0x3C)  # the query frustum's colour in viewer.js
MAX_LINES = 50  # inlier lines per match figure in viewer.js
# map x → East, map z → North, map −y → Up: the synthetic room's y points down
ENU_FROM_MAP = {"rotation": [0.5**0.5, -(0.5**0.5), 0.0, 0.0], "translation": [10.0, 20.0, 3.0]}
ORIGIN = {"latitude": 48.137154, "longitude": 11.576124, "height": 520.0}
# the self-evaluation's colour bands in viewer.js: (upper bound in metres, band, RGB)
ERROR_BANDS = [
    (0.05, "under-5cm", (0x1E, 0x9E, 0x4A)),
    (0.25, "under-25cm", (0xD4, 0xAC, 0x0D)),
    (1.0, "under-1m", (0xE8, 0x73, 0x0C)),
    (float("inf"), "over-1m", (0xA3, 0x15, 0x15)),
]
EVALUATED_REFERENCES, HELD_OUT = 8, 4


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
    app: Any  # the FastAPI app, for its evaluation worker


def _seed_map(api: httpx.Client, name: str, views: list[SyntheticView]) -> str:
    map_id: str = api.post("/v1/maps", json={"name": name}).json()["id"]
    for view in views:
        response = api.post(
            f"/v1/maps/{map_id}/images",
            files={"image": (view.name, encode_png(view.image), "image/png")},
            data={"metadata": json.dumps(image_metadata(view))},
        )
        assert response.status_code == 201, response.text
    return map_id


@contextmanager
def serve_viewer_app(
    folder: Path, localizer: Localizer, **settings: object
) -> Iterator[tuple[str, Any]]:
    """A uvicorn server on a free loopback port, in a thread, for an app with auth on (the
    admin and client keys), SQLite and the SIFT localizer in ``folder``, maps evaluating
    themselves only when asked; yields its URL and the app. ``settings`` override the app's
    settings."""
    values: dict[str, Any] = {
        "database_url": f"sqlite:///{folder / 'viewer.db'}",
        "api_keys": f"{ADMIN_KEY}:admin,{CLIENT_KEY}:client",
        "data_dir": folder / "data",
        "features": "sift",
        "models_dir": folder / "no-models",
        "auto_evaluation_references": 0,  # a map evaluates itself only when a test asks
    }
    app = create_app(Settings(**(values | settings)), localizer=localizer)
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
        yield url, app
    finally:
        server.should_exit = True
        thread.join(timeout=30)


@pytest.fixture(scope="module")
def served(
    tmp_path_factory: pytest.TempPathFactory,
    localizer: Localizer,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> Iterator[Served]:
    tmp = tmp_path_factory.mktemp("viewer")
    with serve_viewer_app(tmp, localizer) as (url, app):
        with httpx.Client(base_url=url, headers={"X-API-Key": ADMIN_KEY}, timeout=60) as api:
            map_id = _seed_map(api, "synthetic room", reference_views[:NUM_REFERENCES])
        query = query_views[0]
        query_png = tmp / "query.png"
        query_png.write_bytes(encode_png(query.image))
        yield Served(url, map_id, query, query_png, app)


@pytest.fixture(scope="module")
def browser() -> Iterator[playwright.Browser]:
    executable = _chromium()
    with playwright.sync_playwright() as p:
        launched = p.chromium.launch(executable_path=executable, args=["--no-sandbox"])
        yield launched
        launched.close()


def _watch_errors(page: playwright.Page) -> list[str]:
    """Uncaught exceptions and console errors of the page, as they happen. Chromium logs each
    refused request as a console error ("Failed to load resource: … 401/404"): those are the
    API's answers the page handles (no key yet, a map without a geo-registration), not
    JavaScript errors."""
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(f"uncaught: {error}"))
    page.on(
        "console",
        lambda message: (
            errors.append(f"console: {message.text}")
            if message.type == "error" and not message.text.startswith("Failed to load resource")
            else None
        ),
    )
    return errors


def open_viewer_map(
    page: playwright.Page, address: str, map_id: str, key: str = CLIENT_KEY
) -> None:
    """Open the viewer at ``address``, type ``key`` and pick the map; returns once it is
    drawn."""
    page.goto(address)
    page.wait_for_selector("body[data-ready=true]")
    page.fill("#api-key", key)
    page.click("#save-key")
    page.click(f"#maps button[data-map-id='{map_id}']")
    page.wait_for_selector("#map-ready[data-ready=true]", state="attached")


def _open_map(page: playwright.Page, served: Served, map_id: str | None = None) -> None:
    """Type the client key and pick the map (``served``'s unless ``map_id``)."""
    open_viewer_map(page, served.url + "/", map_id or served.map_id)
    page.wait_for_selector("#localize:not([disabled])")


def _localize(page: playwright.Page, served: Served, **params: object) -> dict[str, object]:
    """Upload the query and localize on the open map; returns the API's answer as the page
    received it."""
    page.set_input_files("#query-image", str(served.query_png))
    params = {"camera": image_metadata(served.query)["camera"], "top_k": 5, **params}
    page.fill("#params", json.dumps(params))
    with page.expect_response(lambda r: r.url.endswith("/localize")) as answer:
        page.click("#localize")
    assert answer.value.status == 200
    result: dict[str, object] = answer.value.json()
    page.wait_for_selector("#matches[data-ready=true]", state="attached")
    return result


def _localize_in_page(page: playwright.Page, served: Served) -> dict[str, object]:
    _open_map(page, served)
    return _localize(page, served)


def _screenshot(page: playwright.Page, tmp_path: Path, name: str) -> Path:
    path = tmp_path / name
    shot = page.screenshot(path=path, full_page=True)
    assert shot[:8] == b"\x89PNG\r\n\x1a\n"
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(path, ARTIFACTS / name)
    print(f"screenshot: {path}")
    return path


def _pixels(png: bytes) -> np.ndarray:
    bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(int)


def test_viewer_localizes_and_draws(
    browser: playwright.Browser, served: Served, tmp_path: Path
) -> None:
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    errors = _watch_errors(page)
    page.goto(served.url + "/viewer/")
    page.wait_for_selector("body[data-ready=true]")
    # auth is on and the tab has no key yet: the map list is refused, and the page says so
    playwright.expect(page.locator("#status")).to_contain_text("HTTP 401")
    assert page.locator("#scene-note").inner_text() == ""  # three.js loaded

    result = _localize_in_page(page, served)
    assert result["localized"] is True
    playwright.expect(page.locator("#status")).to_contain_text("localized in")

    scene = page.locator("#scene")
    assert scene.get_attribute("data-reference-frusta") == str(NUM_REFERENCES)
    assert scene.get_attribute("data-query-frustum") == "1"
    assert scene.get_attribute("data-candidate-frustum") == "0"
    assert page.locator("#outcome").get_attribute("data-localized") == "true"
    # the page's own pose arithmetic (quaternion → R, centre −Rᵀt) agrees with the server's
    centre = json.loads(scene.get_attribute("data-query-centre") or "null")
    assert np.allclose(centre, result["camera_center"], atol=1e-9)
    # the ground's up: the cameras' mean up, the room's −y (its cameras are near upright)
    up = json.loads(scene.get_attribute("data-up") or "null")
    assert np.dot(up, [0, -1, 0]) > 0.9, up
    assert scene.get_attribute("data-compass") == "0"  # not geo-registered
    assert page.locator("#compass").is_hidden()
    # reference previews are textured on the image planes, a bounded number, loaded lazily
    page.wait_for_function(
        f"Number(document.querySelector('#scene').dataset.thumbnails) >= {NUM_REFERENCES}"
    )
    assert page.locator("#num-inliers").inner_text() == str(result["num_inliers"])
    retrieved = result["retrieved"]
    inliers = result["inliers"]
    assert isinstance(retrieved, list) and isinstance(inliers, list) and len(inliers) >= 2
    assert page.locator("li.retrieved").count() == len(retrieved)

    # one match figure at a time, at most MAX_LINES lines; next / previous page through them
    view = page.locator("canvas.match-view")
    assert view.count() == 1
    assert page.locator("#match-position").inner_text() == f"1 / {len(inliers)}"
    for index in (0, 1, 0):
        if index != int(view.get_attribute("data-index") or "-1"):
            page.click("#match-next" if index == 1 else "#match-prev")
            page.wait_for_selector(
                f"#matches[data-ready=true] canvas.match-view[data-index='{index}']"
            )
        pair = inliers[index]
        assert view.get_attribute("data-image-id") == pair["image_id"]
        assert view.get_attribute("data-inliers") == str(len(pair["query_xy"]))
        lines = int(view.get_attribute("data-lines") or "-1")
        assert lines == min(MAX_LINES, len(pair["query_xy"])), lines

    shot = _screenshot(page, tmp_path, "viewer.png")
    assert shot.stat().st_size > 0
    # the 3D view drew the query frustum in its colour ...
    drawn = _pixels(scene.screenshot())
    query_pixels = np.all(np.abs(drawn - QUERY_RGB) < 40, axis=-1).sum()
    # (1-px lines: 43 on the first run, 0 with nothing drawn)
    assert query_pixels > 20, f"{query_pixels} pixels of the query frustum's colour"
    # ... and the match figure holds the reference preview, not the grey stand-in
    match_view = _pixels(view.screenshot())
    right = match_view[:, match_view.shape[1] // 2 + 20 :]
    assert right.std() > 20, "the reference half of the match view is blank"
    assert errors == []
    page.close()


def test_viewer_shows_a_failed_query_as_failed(
    browser: playwright.Browser, served: Served, tmp_path: Path
) -> None:
    """Above the answer's confidence the same query is not localized (low_confidence): the
    header says so with the reason, and the candidate pose is drawn dashed, not as the query."""
    page = browser.new_page(viewport={"width": 1200, "height": 900})
    errors = _watch_errors(page)
    answered = _localize_in_page(page, served)
    assert answered["localized"] is True
    confidence = answered["confidence"]
    assert isinstance(confidence, float) and confidence < 1.0
    refused = _localize(page, served, min_confidence=(confidence + 1.0) / 2.0)
    assert refused["localized"] is False and refused["reason"] == "low_confidence"

    playwright.expect(page.locator("#status")).to_contain_text("not localized: low_confidence")
    assert "localized in" not in page.locator("#status").inner_text()
    assert page.locator("#outcome").get_attribute("data-localized") == "false"
    playwright.expect(page.locator("#outcome")).to_contain_text("Not localized: low_confidence")
    scene = page.locator("#scene")
    assert scene.get_attribute("data-query-frustum") == "0"
    assert scene.get_attribute("data-candidate-frustum") == "1"
    candidate = json.loads(scene.get_attribute("data-candidate-centre") or "null")
    assert np.allclose(candidate, answered["camera_center"], atol=1e-9)
    _screenshot(page, tmp_path, "viewer-not-localized.png")
    assert errors == []
    page.close()


def test_viewer_geo_registered_map(
    browser: playwright.Browser, served: Served, tmp_path: Path
) -> None:
    """On a geo-registered map the ground carries a North arrow (the corner compass turns with
    the view) and the side panel shows the answer's GeoPose."""
    with httpx.Client(base_url=served.url, headers={"X-API-Key": ADMIN_KEY}) as api:
        url = f"/v1/maps/{served.map_id}/geo-registration"
        response = api.put(url, json={"origin": ORIGIN, "enu_from_map": ENU_FROM_MAP})
        assert response.status_code == 200, response.text
        try:
            page = browser.new_page(viewport={"width": 1200, "height": 900})
            errors = _watch_errors(page)
            _open_map(page, served)
            scene = page.locator("#scene")
            assert scene.get_attribute("data-compass") == "1"
            # up is ENU's up through the registration: map −y
            up = json.loads(scene.get_attribute("data-up") or "null")
            assert np.allclose(up, [0, -1, 0], atol=1e-6), up
            assert page.locator("#compass").is_visible()
            assert page.locator("#geo").get_attribute("data-registered") == "true"
            playwright.expect(page.locator("#geo-registration")).to_contain_text("48.137")

            result = _localize(page, served)
            assert result["localized"] is True
            geopose = result["geopose"]
            assert isinstance(geopose, dict)
            panel = page.locator("#geopose")
            playwright.expect(panel).to_contain_text("lat")
            assert float(panel.get_attribute("data-lat") or "nan") == geopose["position"]["lat"]
            assert float(panel.get_attribute("data-lon") or "nan") == geopose["position"]["lon"]
            assert (
                page.locator("#geopose dd[data-field=lon]")
                .inner_text()
                .startswith(f"{geopose['position']['lon']:.6f}"[:-1])
            )
            assert "quaternion" in panel.inner_text()
            _screenshot(page, tmp_path, "viewer-geo.png")
            assert errors == []
            page.close()
        finally:
            assert api.delete(url).status_code == 204


def test_viewer_without_three_js_still_localizes(
    browser: playwright.Browser, served: Served, tmp_path: Path
) -> None:
    page = browser.new_page(viewport={"width": 1200, "height": 900})
    errors = _watch_errors(page)
    page.route("**/viewer/vendor/**", lambda route: route.abort())  # as if never installed
    result = _localize_in_page(page, served)
    playwright.expect(page.locator("#scene-note")).to_contain_text("three.js is not installed")
    assert page.locator("#scene").get_attribute("data-reference-frusta") == "0"
    assert page.locator("#num-inliers").inner_text() == str(result["num_inliers"])
    inliers = result["inliers"]
    assert isinstance(inliers, list) and inliers
    assert page.locator("canvas.match-view").count() == 1
    assert page.locator("#match-position").inner_text() == f"1 / {len(inliers)}"
    _screenshot(page, tmp_path, "viewer-without-three.png")
    assert errors == [], errors
    page.close()


def _band(reference: dict[str, Any]) -> tuple[str, tuple[int, int, int]]:
    error = reference["position_error_m"] if reference["localized"] else None
    if error is None:  # not localized
        return ERROR_BANDS[-1][1:]
    return next((band, rgb) for top, band, rgb in ERROR_BANDS if error < top)


def test_viewer_colours_the_self_evaluation(
    browser: playwright.Browser,
    served: Served,
    reference_views: list[SyntheticView],
    tmp_path: Path,
) -> None:
    """Without an evaluation the panel says how to start one; a queued one shows as queued;
    once done, exactly the held-out references are coloured by their held-out error (the
    panel, the legend, the frusta's dots in the pixels), and a dot names its error when
    hovered and picks it when clicked."""
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    errors = _watch_errors(page)
    _open_map(page, served)
    panel = page.locator("#evaluation")
    assert panel.get_attribute("data-state") == "none"
    command = page.locator("#eval-command").inner_text()
    assert command.startswith(f'slloc self-evaluate --url {served.url} --map "synthetic room"')
    playwright.expect(panel).to_contain_text(f"POST /v1/maps/{served.map_id}/evaluations")
    assert page.locator("#scene").get_attribute("data-held-out-frusta") == "0"

    with httpx.Client(base_url=served.url, headers={"X-API-Key": ADMIN_KEY}, timeout=60) as api:
        views = reference_views[:EVALUATED_REFERENCES]
        map_id = _seed_map(api, "evaluated room", views)
        try:
            # the worker's one thread is held: the evaluation stays queued while the page looks
            release = threading.Event()
            served.app.state.evaluator.worker.schedule("hold", release.wait)
            try:
                started = api.post(
                    f"/v1/maps/{map_id}/evaluations",
                    json={"configurations": ["sift"], "sample_size": HELD_OUT},
                )
                assert started.status_code == 202, started.text
                _open_map(page, served, map_id)
                assert panel.get_attribute("data-state") == "queued"
                progress = page.locator("#eval-progress")
                assert progress.get_attribute("data-state") == "queued"
                playwright.expect(progress).to_contain_text("queued")
                assert page.locator("#eval-command").count() == 0  # one is on its way
                assert page.locator("#scene").get_attribute("data-held-out-frusta") == "0"
            finally:
                release.set()
            location = started.headers["Location"]
            assert wait_until(
                lambda: api.get(location).json()["state"] not in ("queued", "running"),
                timeout_s=180.0,
            )
            evaluation = api.get(location).json()
            assert evaluation["state"] == "done", evaluation

            # the page looks again by itself (after 4 s, then less and less often)
            page.wait_for_selector(
                "#evaluation[data-state=done]", state="attached", timeout=240_000
            )
            result = evaluation["result"]
            assert result["served"] == "sift"
            references = result["configurations"]["sift"]["references"]
            assert len(references) == HELD_OUT
            expected = {r["image_id"]: _band(r)[0] for r in references}
            assert panel.get_attribute("data-evaluation-id") == evaluation["id"]
            assert panel.get_attribute("data-configuration") == "sift"
            assert panel.get_attribute("data-recommended") == (result["recommended"] or "")
            assert page.locator("#eval-date").get_attribute("datetime") is not None
            playwright.expect(page.locator("#eval-recommended")).to_contain_text(
                f"Recommended: {result['recommended']}"
            )
            assert progress.is_hidden()
            row = page.locator("#eval-table tr[data-configuration=sift]")
            recall = result["configurations"]["sift"]["recall"]
            for field, key in (("recall-5cm-5deg", "5cm_5deg"), ("recall-25cm-2deg", "25cm_2deg")):
                cell = row.locator(f"td[data-field={field}]").inner_text()
                assert cell == f"{100 * recall[key]:.0f}%", (field, cell)
            assert "ms" in row.locator("td[data-field=median-latency]").inner_text()
            # exactly the held-out references are coloured, each in its error's band
            scene = page.locator("#scene")
            assert scene.get_attribute("data-held-out-frusta") == str(HELD_OUT)
            assert json.loads(scene.get_attribute("data-held-out") or "null") == expected
            items = page.locator("#eval-references li")
            assert items.count() == HELD_OUT
            listed = {
                items.nth(i).get_attribute("data-image-id"): items.nth(i).get_attribute("data-band")
                for i in range(HELD_OUT)
            }
            assert listed == expected
            for _, band, _ in ERROR_BANDS:
                count = sum(1 for b in expected.values() if b == band)
                legend = page.locator(f"#eval-legend em[data-band={band}]").inner_text()
                assert legend.endswith(f"({count})"), legend
            # the dots are drawn in their band's colour
            drawn = _pixels(scene.screenshot())
            for band, rgb in {_band(r)[0]: _band(r)[1] for r in references}.items():
                coloured = np.all(np.abs(drawn - rgb) < 12, axis=-1).sum()
                assert coloured > 20, f"{coloured} pixels of {band}'s colour"

            # picking: from the list, then by hovering and clicking a dot in the 3D view
            first, second = references[0], references[1]
            page.click(f"#eval-references li[data-image-id='{first['image_id']}']")
            selected = page.locator("#eval-selected")
            assert selected.get_attribute("data-image-id") == first["image_id"]
            assert selected.get_attribute("data-band") == expected[first["image_id"]]
            playwright.expect(selected).to_contain_text(f"{first['name']} held out")
            x, y = json.loads(selected.get_attribute("data-screen") or "null")
            box = scene.bounding_box()
            assert box is not None
            assert (
                box["x"] < x < box["x"] + box["width"] and box["y"] < y < box["y"] + box["height"]
            )
            page.click(f"#eval-references li[data-image-id='{second['image_id']}']")
            assert selected.get_attribute("data-image-id") == second["image_id"]
            page.mouse.move(x, y)
            tip = page.locator("#eval-tip")
            playwright.expect(tip).to_be_visible()
            assert tip.get_attribute("data-image-id") == first["image_id"]
            playwright.expect(tip).to_contain_text(first["name"])
            page.mouse.click(x, y)
            assert selected.get_attribute("data-image-id") == first["image_id"]
            _screenshot(page, tmp_path, "viewer-evaluation.png")
            assert errors == [], errors
            page.close()
        finally:
            assert api.delete(f"/v1/maps/{map_id}").status_code == 204
