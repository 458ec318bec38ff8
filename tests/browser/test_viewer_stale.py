"""The viewer's "Stale references" panel in a real headless Chromium (as tests/browser/
test_viewer.py drives it): a uvicorn server with auth on, a map of four synthetic references,
one of them flagged stale in the database as a capture session or a self-evaluation leaves it
(the API tests check the flagging itself). Opened with the client key, the panel names the
flagged reference with its reason, and the 3D view draws its frustum dashed; a map with no
flag says so."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import httpx
import pytest

from db.models import ReferenceImage
from services.localization.localizer import Localizer
from tests.browser.test_viewer import (
    ADMIN_KEY,
    _chromium,
    _screenshot,
    _seed_map,
    _watch_errors,
    open_viewer_map,
    serve_viewer_app,
)
from tools.synthetic.scene import SyntheticView

playwright = pytest.importorskip("playwright.sync_api", reason="playwright is in the dev extra")

REASON = "self-evaluation 1234: 2 view(s) that cover it matched it with at most 3 inliers"


@pytest.fixture
def server(tmp_path: Path, localizer: Localizer) -> Iterator[tuple[str, Any]]:
    with serve_viewer_app(tmp_path, localizer) as served:
        yield served


def test_viewer_lists_stale_references(
    server: tuple[str, Any], reference_views: list[SyntheticView], tmp_path: Path
) -> None:
    url, app = server
    with httpx.Client(base_url=url, headers={"X-API-Key": ADMIN_KEY}, timeout=60) as api:
        flagged_map = _seed_map(api, "flagged", reference_views[:4])
        clean_map = _seed_map(api, "clean", reference_views[4:6])
        images = api.get(f"/v1/maps/{flagged_map}/images").json()["items"]
    stale = next(image for image in images if image["name"] == reference_views[2].name)
    with app.state.sessions.begin() as session:
        row = session.get(ReferenceImage, stale["id"])
        row.stale_since, row.stale_reason = datetime.now(UTC), REASON

    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=_chromium(), args=["--no-sandbox"])
        page = browser.new_page(viewport={"width": 1400, "height": 1000})
        errors = _watch_errors(page)
        open_viewer_map(page, url + "/viewer/", flagged_map)
        panel = page.locator("#stale")
        assert panel.get_attribute("data-count") == "1"
        playwright.expect(page.locator("#stale-summary")).to_contain_text(
            "1 of 4 references flagged stale"
        )
        [item] = page.locator("#stale-list li").all()
        assert item.get_attribute("data-image-id") == stale["id"]
        assert item.locator("[data-field=name]").inner_text() == stale["name"]
        playwright.expect(item.locator("[data-field=reason]")).to_contain_text(REASON)
        scene = page.locator("#scene")
        assert scene.get_attribute("data-reference-frusta") == "4"
        assert scene.get_attribute("data-stale-frusta") == "1"
        _screenshot(page, tmp_path, "viewer-stale.png")

        page.click(f"#maps button[data-map-id='{clean_map}']")
        page.wait_for_selector("#stale[data-count='0']", state="attached")
        playwright.expect(page.locator("#stale-summary")).to_have_text(
            "No reference is flagged stale."
        )
        assert page.locator("#stale-list li").count() == 0
        assert scene.get_attribute("data-stale-frusta") == "0"
        browser.close()
    assert errors == [], errors
