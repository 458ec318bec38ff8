"""The viewer's coverage cells in a real headless Chromium (as tests/browser/test_viewer.py
drives it): a uvicorn server with auth on, a map of eight synthetic references measured by a
self-evaluation whose held-out queries all fail (a hold-out radius over the whole map leaves
them nothing to match, so their cells are weak), and a second map of two references without
one. Opened with the client key, the page's "Coverage" panel says how many cells the API
answers and how many are weak, lists the weak ones' reasons, and the 3D view holds one square
per cell; the second map's cells replace the first's."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

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
from tests.polling import wait_until
from tools.synthetic.scene import SyntheticView

playwright = pytest.importorskip("playwright.sync_api", reason="playwright is in the dev extra")

REFERENCES, HELD_OUT = 8, 4


@pytest.fixture
def server(tmp_path: Path, localizer: Localizer) -> Iterator[str]:
    with serve_viewer_app(tmp_path, localizer) as (url, _):
        yield url


def _expect_cells(page: playwright.Page, coverage: dict[str, Any]) -> None:
    """The panel and the 3D view show the API's ``coverage``."""
    cells = coverage["cells"]
    assert cells
    weak = [cell for cell in cells if cell["weak"]]
    assert coverage["weak"] == len(weak)
    panel = page.locator("#coverage")
    assert panel.get_attribute("data-state") == "done"
    assert panel.get_attribute("data-cells") == str(len(cells))
    assert panel.get_attribute("data-weak") == str(len(weak))
    plural = "" if len(cells) == 1 else "s"
    playwright.expect(page.locator("#coverage-summary")).to_contain_text(
        f"{len(cells)} cell{plural}, {len(weak)} weak"
    )
    assert page.locator("#scene").get_attribute("data-coverage-cells") == str(len(cells))
    items = page.locator("#coverage-weak li")
    assert items.count() == min(len(weak), 10)
    for k, cell in enumerate(weak[:10]):
        assert items.nth(k).inner_text() == f"cell ({cell['i']}, {cell['j']}): " + "; ".join(
            cell["why"]
        )


def test_viewer_draws_the_coverage_cells(
    server: str, reference_views: list[SyntheticView], tmp_path: Path
) -> None:
    with httpx.Client(base_url=server, headers={"X-API-Key": ADMIN_KEY}, timeout=60) as api:
        map_id = _seed_map(api, "measured room", reference_views[:REFERENCES])
        other_id = _seed_map(api, "two views", reference_views[REFERENCES : REFERENCES + 2])
        started = api.post(
            f"/v1/maps/{map_id}/evaluations",
            json={"configurations": ["sift"], "sample_size": HELD_OUT, "holdout_radius_m": 1000},
        )
        assert started.status_code == 202, started.text
        location = started.headers["Location"]
        assert wait_until(
            lambda: api.get(location).json()["state"] not in ("queued", "running"),
            timeout_s=180.0,
        )
        evaluation = api.get(location).json()
        assert evaluation["state"] == "done", evaluation
        coverage = api.get(f"/v1/maps/{map_id}/coverage").json()
        assert coverage["evaluation_id"] == evaluation["id"]
        assert coverage["weak"] >= 1  # every held-out query failed
        other = api.get(f"/v1/maps/{other_id}/coverage").json()
        assert other["evaluation_id"] is None

    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=_chromium(), args=["--no-sandbox"])
        page = browser.new_page(viewport={"width": 1400, "height": 1000})
        errors = _watch_errors(page)
        open_viewer_map(page, server + "/viewer/", map_id)
        _expect_cells(page, coverage)
        assert page.locator("#coverage").get_attribute("data-evaluation-id") == evaluation["id"]
        held_out = [cell for cell in coverage["cells"] if cell["held_out"]]
        assert sum(cell["held_out"] for cell in held_out) == HELD_OUT
        playwright.expect(page.locator("#coverage-weak")).to_contain_text(
            "references held out failed"
        )
        _screenshot(page, tmp_path, "viewer-coverage.png")

        # another map: its cells replace the first's (no evaluation: single references only)
        page.click(f"#maps button[data-map-id='{other_id}']")
        page.wait_for_selector("#map-ready[data-ready=true]", state="attached")
        _expect_cells(page, other)
        assert page.locator("#coverage").get_attribute("data-evaluation-id") is None
        playwright.expect(page.locator("#coverage-summary")).to_contain_text(
            "no finished self-evaluation"
        )
        assert errors == [], errors
        browser.close()
