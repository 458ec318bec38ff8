"""A request id for every request, and one access log line per request."""

from __future__ import annotations

import logging
import re
import time
import uuid
from contextvars import ContextVar

from starlette.types import ASGIApp, Message, Receive, Scope, Send

REQUEST_ID_HEADER = "X-Request-ID"
_HEADER_KEY = REQUEST_ID_HEADER.lower().encode()

# an incoming id is kept when it is a short token that cannot break a log line or a header
_SAFE_REQUEST_ID = re.compile(r"[A-Za-z0-9._-]{1,64}")

_request_id: ContextVar[str | None] = ContextVar("request_id", default=None)

access_logger = logging.getLogger("slloc.access")


def current_request_id() -> str | None:
    """The id of the request being handled; None outside a request. Worker threads the
    request runs work on (``run_in_threadpool``, ``anyio.to_thread``) see it too."""
    return _request_id.get()


def request_id_from(header: str | None) -> str:
    """``header`` when it is a safe token, else a new id (32 hex digits)."""
    if header is not None and _SAFE_REQUEST_ID.fullmatch(header):
        return header
    return uuid.uuid4().hex


class RequestContext:
    """ASGI middleware, outermost: gives the request its id (``current_request_id()``),
    echoes it in the ``X-Request-ID`` response header and logs an access line (method, path,
    status, duration) on the ``slloc.access`` logger."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        header = next((v for k, v in scope["headers"] if k == _HEADER_KEY), None)
        request_id = request_id_from(header.decode("latin-1") if header is not None else None)
        token = _request_id.set(request_id)
        status = 500  # an error raised before any answer is answered 500 outside
        start = time.perf_counter()

        async def send_with_id(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
                headers = list(message.get("headers", []))
                headers.append((_HEADER_KEY, request_id.encode()))
                message = {**message, "headers": headers}
            await send(message)

        try:
            await self.app(scope, receive, send_with_id)
        except Exception:
            # the id stays set: the server's 500 answer and its error log come after this
            _log_access(scope, status, start)
            raise
        _log_access(scope, status, start)
        _request_id.reset(token)


def _log_access(scope: Scope, status: int, start: float) -> None:
    duration_ms = round((time.perf_counter() - start) * 1000, 1)
    method, path = scope["method"], scope["path"]
    access_logger.info(
        "%s %s %d %.1f ms",
        method,
        path,
        status,
        duration_ms,
        extra={"method": method, "path": path, "status": status, "duration_ms": duration_ms},
    )
