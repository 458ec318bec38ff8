"""Refuses request bodies over the upload limit before they are read, and admits bodies only
within the memory the server budgets for them (``SLLOC_BODY_MEMORY_MIB``)."""

from __future__ import annotations

import threading

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.errors import send_problem_and_close
from services.runtime.memory import JSON_BODY_FACTOR

# seconds a client is asked to wait when the body memory is taken by other requests
BODY_MEMORY_RETRY_AFTER_S = 1


class BodyMemory:
    """The bytes that request bodies being received or handled may hold at once."""

    def __init__(self, budget_bytes: int) -> None:
        self.budget_bytes = budget_bytes
        self.held_bytes = 0
        self._lock = threading.Lock()

    def reserve(self, nbytes: int) -> bool:
        with self._lock:
            if self.held_bytes + nbytes > self.budget_bytes:
                return False
            self.held_bytes += nbytes
            return True

    def release(self, nbytes: int) -> None:
        with self._lock:
            self.held_bytes -= nbytes


def body_cost(headers: dict[bytes, bytes], max_bytes: int) -> int:
    """The memory a request's body may take: its declared length (a chunked body: the body
    limit), times ``JSON_BODY_FACTOR`` for a JSON body, parsed whole; 0 without a body."""
    length = headers.get(b"content-length")
    if length is not None and length.isdigit():
        size = int(length)
    elif b"chunked" in headers.get(b"transfer-encoding", b"").lower():
        size = max_bytes
    else:
        return 0
    json_body = b"json" in headers.get(b"content-type", b"").lower()
    return int(size * JSON_BODY_FACTOR) if json_body else size


class BodySizeLimit:
    """ASGI middleware: 413 problem+json when Content-Length exceeds ``max_bytes``, and the
    same when a chunked body grows past it; 503 with Retry-After when the body's cost
    (``body_cost``) does not fit in ``memory`` beside the bodies already admitted."""

    def __init__(self, app: ASGIApp, max_bytes: int, memory: BodyMemory) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.memory = memory

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers", []))
        length = headers.get(b"content-length")
        if length is not None and length.isdigit() and int(length) > self.max_bytes:
            await self._reject(scope, send)
            return
        cost = body_cost(headers, self.max_bytes)
        if not self.memory.reserve(cost):
            await self._busy(scope, send)
            return
        try:
            await self._limited(scope, receive, send)
        finally:
            self.memory.release(cost)

    async def _limited(self, scope: Scope, receive: Receive, send: Send) -> None:
        received = 0

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    # an HTTPException passes the framework's body parsing unwrapped, so the
                    # exception handlers answer it; one raised outside them lands below
                    raise BodyTooLargeError(self.max_bytes)
            return message

        try:
            await self.app(scope, limited_receive, send)
        except BodyTooLargeError:
            await self._reject(scope, send)

    async def _reject(self, scope: Scope, send: Send) -> None:
        await send_problem_and_close(
            scope,
            send,
            413,
            "payload-too-large",
            "Payload too large",
            _detail(self.max_bytes),
        )

    async def _busy(self, scope: Scope, send: Send) -> None:
        detail = (
            f"the server is receiving other request bodies up to its body memory "
            f"({self.memory.budget_bytes} bytes); retry after {BODY_MEMORY_RETRY_AFTER_S} s"
        )
        retry = [(b"retry-after", str(BODY_MEMORY_RETRY_AFTER_S).encode())]
        await send_problem_and_close(
            scope, send, 503, "body-memory-full", "Service busy", detail, retry
        )


class BodyTooLargeError(HTTPException):
    """A chunked request body grew past the limit; the rest of it is not read, so the
    connection closes after the answer."""

    def __init__(self, max_bytes: int) -> None:
        super().__init__(413, _detail(max_bytes), headers={"Connection": "close"})


def _detail(max_bytes: int) -> str:
    return f"request body exceeds {max_bytes} bytes"
