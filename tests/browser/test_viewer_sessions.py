"""The viewer's "Capture sessions" panel in a real headless Chromium (as tests/browser/
test_viewer.py drives it): a uvicorn server with auth on, an empty map bootstrapped by one
capture session of four synthetic views, and the page opened with the admin key (the panel
lists the session: queued while the capture worker is held, then added by itself) and with a
client key (the API answers 403: the panel says that an admin key is needed)."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest

from services.localization.localizer import Localizer
from tests.browser.test_viewer import (
    ADMIN_KEY,
    CLIENT_KEY,
    _chromium,
    _screenshot,
    _watch_errors,
    open_viewer_map,
    serve_viewer_app,
)
from tests.conftest import image_metadata
from tests.polling import wait_until
from tools.synthetic.scene import SyntheticView, encode_png

playwright = pytest.importorskip("playwright.sync_api", reason="playwright is in the dev extra")

FRAMES = 4


@dataclass(frozen=True)
class Server:
    url: str
    app: Any  # the FastAPI app, for its capture worker


@pytest.fixture
def server(tmp_path: Path, localizer: Localizer) -> Iterator[Server]:
    with serve_viewer_app(tmp_path, localizer) as (url, app):
        yield Server(url, app)


def _frame(api: httpx.Client, path: str, view: SyntheticView) -> None:
    """Uploads the view as a frame whose session pose is its world pose (a bootstrap keeps
    the session's frame)."""
    metadata = image_metadata(view)
    metadata["cam_from_session"] = metadata.pop("cam_from_world")
    response = api.post(
        f"{path}/frames",
        files={"image": (view.name, encode_png(view.image), "image/png")},
        data={"metadata": json.dumps(metadata)},
    )
    assert response.status_code == 201, response.text


def test_viewer_lists_capture_sessions(
    server: Server, reference_views: list[SyntheticView], tmp_path: Path
) -> None:
    with httpx.Client(base_url=server.url, headers={"X-API-Key": ADMIN_KEY}, timeout=60) as api:
        map_id = api.post("/v1/maps", json={"name": "captured room"}).json()["id"]
        created = api.post(f"/v1/maps/{map_id}/sessions", json={"name": "walk-1"})
        assert created.status_code == 201, created.text
        path = f"/v1/maps/{map_id}/sessions/{created.json()['id']}"
        for view in reference_views[:FRAMES]:
            _frame(api, path, view)

        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=_chromium(), args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            errors = _watch_errors(page)
            # the capture worker's one thread is held: the session stays queued while the
            # page looks, then the page looks again by itself
            release = threading.Event()
            server.app.state.capture_runner.worker.schedule("hold", release.wait)
            try:
                assert api.post(f"{path}/submit").status_code == 202
                open_viewer_map(page, server.url + "/viewer/", map_id, ADMIN_KEY)
                panel = page.locator("#sessions")
                assert panel.get_attribute("data-state") == "active"
                item = page.locator(f"#sessions-list li[data-session-id='{created.json()['id']}']")
                assert item.get_attribute("data-state") == "queued"
                assert page.locator("#sessions-refresh").is_visible()
            finally:
                release.set()
            assert wait_until(
                lambda: api.get(path).json()["state"] not in ("queued", "aligning", "adding"),
                timeout_s=180.0,
            )
            session = api.get(path).json()
            assert session["state"] == "added", session
            assert session["alignment"]["mode"] == "bootstrap"

            page.wait_for_selector(
                "#sessions[data-state=decided]", state="attached", timeout=60_000
            )
            assert item.get_attribute("data-state") == "added"
            assert item.locator("[data-field=name]").inner_text() == "walk-1"
            assert item.locator("[data-field=state]").inner_text() == "added"
            assert item.locator("[data-field=mode]").inner_text() == "bootstrap"
            assert item.locator("[data-field=scale]").inner_text() == "scale 1.0000"
            playwright.expect(item).to_contain_text(f"{FRAMES} frames")
            assert page.locator("#sessions-refresh").is_hidden()
            # seen queued, now added: the map has references the page has not drawn
            playwright.expect(page.locator("#sessions-summary")).to_contain_text(
                "pick the map again"
            )
            _screenshot(page, tmp_path, "viewer-sessions.png")

            # a client key may not read sessions: a note, not an error
            open_viewer_map(page, server.url + "/viewer/", map_id, CLIENT_KEY)
            assert panel.get_attribute("data-state") == "forbidden"
            playwright.expect(page.locator("#sessions-summary")).to_contain_text("admin key")
            assert page.locator("#sessions-list li").count() == 0
            assert errors == [], errors
            browser.close()
