"""The map viewer: a static page at ``/viewer/`` (``/`` redirects there) that calls the API
from the browser. Its three.js comes from the npm registry at install time
(``scripts/build_web.sh`` fills ``app/web/vendor/``); without it the page still lists maps,
localizes and draws matches, and says that the 3D view is off."""

from __future__ import annotations

import logging
from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import RedirectResponse
from fastapi.staticfiles import StaticFiles

logger = logging.getLogger(__name__)

WEB_DIR = Path(__file__).resolve().parent / "web"
VENDOR_DIR = WEB_DIR / "vendor"
# what scripts/build_web.sh copies from the `three` package
VENDOR_FILES = ("three.module.js", "three.core.js", "addons/controls/OrbitControls.js")


def vendor_installed() -> bool:
    """Whether the page's three.js modules are in place."""
    return all((VENDOR_DIR / name).is_file() for name in VENDOR_FILES)


def install_viewer(app: FastAPI) -> None:
    """Serve the viewer at ``/viewer/``; ``/`` redirects there. Nothing here needs a key: the
    page sends the key the user types (kept in the tab's sessionStorage) with each API call."""

    async def root() -> RedirectResponse:
        return RedirectResponse("/viewer/")

    app.add_api_route("/", root, include_in_schema=False)
    app.mount("/viewer", StaticFiles(directory=WEB_DIR, html=True), name="viewer")
    if not vendor_installed():
        logger.warning(
            "viewer: three.js is not installed in %s (run scripts/build_web.sh, which needs "
            "npm): /viewer/ works without its 3D view",
            VENDOR_DIR,
        )
