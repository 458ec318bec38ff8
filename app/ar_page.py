"""The browser AR client: a static page at ``/ar`` that localizes the live camera (the
browser's ``getUserMedia``) through the API every few seconds or on demand and draws the map's
reference cameras over the video at the localized pose. Its files are ``app/web/ar.*``, served
with the viewer's under ``/viewer/``; its three.js is the viewer's (``scripts/build_web.sh``).
Without three.js the page still localizes and shows the pose, without the overlay."""

from __future__ import annotations

from fastapi import FastAPI
from fastapi.responses import FileResponse

from app.viewer import WEB_DIR

AR_PAGE = WEB_DIR / "ar.html"


def install_ar_page(app: FastAPI) -> None:
    """Serve the AR client at ``/ar`` (``/ar/`` redirects there, query string kept). Like the
    viewer it needs no key: the page sends the key the user gives with each API call."""

    async def ar_page() -> FileResponse:
        return FileResponse(AR_PAGE, media_type="text/html")

    app.add_api_route("/ar", ar_page, methods=["GET", "HEAD"], include_in_schema=False)
