"""What ``slloc serve`` does so that idle and slow clients cannot starve the service, its probes
above all (issue "Holds under every fault", N7), built on public interfaces only:

- ``IdleConnectionGuard``, the HTTP protocol ``slloc serve`` hands uvicorn (its ``http`` option
  takes an ``asyncio.Protocol`` class): uvicorn's own h11 protocol, composed (not subclassed)
  behind the asyncio protocol and transport interfaces. It closes a connection on which the
  client owes the server bytes (a request head, or the next request after an answer) and has
  sent none for ``timeout_keep_alive`` seconds. uvicorn alone times only a connection idle after
  a response, and stops timing at its first byte.
- ``ClientAdmission``, an ASGI middleware: requests in flight at once, in all
  (``SLLOC_LIMIT_CONCURRENCY``) and per client address (``SLLOC_MAX_REQUESTS_PER_CLIENT``);
  more get 503 with ``Retry-After``. The probes, ``/v1/health`` and ``/metrics`` are not
  counted, so they are answered whatever other clients hold. A request body must arrive within
  ``SLLOC_REQUEST_BODY_TIMEOUT_S`` of its head (else 408, connection closed).

uvicorn's ``limit_concurrency`` is off: it counts open connections, so idle ones made every
request, probes included, answer 503.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any, cast

from starlette.types import ASGIApp, Message, Receive, Scope, Send
from uvicorn.config import Config
from uvicorn.protocols.http.h11_impl import H11Protocol
from uvicorn.server import ServerState

from app.errors import send_problem_and_close

logger = logging.getLogger(__name__)

# h11's bound on a request head still being received (request line and headers), bytes
MAX_REQUEST_HEAD_BYTES = 16 * 1024
# answered outside the admission: probes, health and metrics are cheap and must stay answered
EXEMPT_PATHS = frozenset(("/livez", "/readyz", "/v1/health", "/metrics"))
RETRY_AFTER_S = 1
_HEAD_END = b"\r\n\r\n"


class _WatchedTransport:
    """The transport the inner protocol writes to: the real one, telling the guard of writes."""

    def __init__(self, transport: asyncio.Transport, guard: IdleConnectionGuard) -> None:
        self._transport = transport
        self._guard = guard

    def write(self, data: bytes | bytearray | memoryview) -> None:
        self._transport.write(data)
        self._guard.server_wrote()

    def writelines(self, lines: Any) -> None:
        self._transport.writelines(lines)
        self._guard.server_wrote()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._transport, name)


class IdleConnectionGuard(asyncio.Protocol):
    """uvicorn's h11 protocol behind a silence timer (see the module). The client owes bytes
    from the connection's start until a request head is complete, and again from each write of
    the server (an answer, or ``100 Continue``); while it owes them and is silent for
    ``config.timeout_keep_alive`` seconds, the connection is closed. While the server works on
    a request (a head complete, nothing written yet) the timer is off."""

    def __init__(
        self,
        config: Config,
        server_state: ServerState,
        app_state: dict[str, Any],
        _loop: asyncio.AbstractEventLoop | None = None,
    ) -> None:
        self.inner = H11Protocol(config, server_state, app_state, _loop)
        self.loop = _loop or asyncio.get_event_loop()
        self.timeout_s = float(config.timeout_keep_alive)
        self.transport: asyncio.Transport | None = None
        self.client_owes = True
        self._tail = b""
        self._timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.Transport, transport)
        self.inner.connection_made(cast(asyncio.Transport, _WatchedTransport(self.transport, self)))
        self._arm()

    def data_received(self, data: bytes) -> None:
        if self.client_owes:
            seen = self._tail + data
            if _HEAD_END in seen:
                self.client_owes = False
                self._tail = b""
            else:
                self._tail = seen[-(len(_HEAD_END) - 1) :]
        if self.client_owes:
            self._arm()
        else:
            self._cancel()
        self.inner.data_received(data)

    def server_wrote(self) -> None:
        self.client_owes = True
        self._tail = b""
        self._arm()

    def eof_received(self) -> bool | None:
        self.inner.eof_received()
        return None  # the transport closes itself

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel()
        self.inner.connection_lost(exc)

    def pause_writing(self) -> None:
        self.inner.pause_writing()

    def resume_writing(self) -> None:
        self.inner.resume_writing()

    def _arm(self) -> None:
        self._cancel()
        if self.transport is not None and not self.transport.is_closing():
            self._timer = self.loop.call_later(self.timeout_s, self._silent)

    def _cancel(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _silent(self) -> None:
        self._timer = None
        if self.client_owes and self.transport is not None and not self.transport.is_closing():
            self.transport.close()


class ClientAdmission:
    """ASGI middleware: at most ``max_in_flight`` requests at once and ``max_per_client`` per
    client address (``scope["client"]``, after uvicorn's proxy headers); more get 503
    problem+json with ``Retry-After``. Paths in ``EXEMPT_PATHS`` are not counted. A request's
    body must arrive within ``body_timeout_s`` of its head: past that the app is told the client
    left and the answer is 408 with ``Connection: close``."""

    def __init__(
        self, app: ASGIApp, max_in_flight: int, max_per_client: int, body_timeout_s: float
    ) -> None:
        self.app = app
        self.max_in_flight = max_in_flight
        self.max_per_client = max_per_client
        self.body_timeout_s = body_timeout_s
        self.in_flight = 0
        self.per_client: dict[str, int] = {}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope.get("path") in EXEMPT_PATHS:
            await self.app(scope, receive, send)
            return
        client = scope.get("client")
        host = str(client[0]) if client else ""
        held = self.per_client.get(host, 0)
        if self.in_flight >= self.max_in_flight or held >= self.max_per_client:
            whose = "this client's" if held >= self.max_per_client else "the server's"
            await send_problem_and_close(
                scope,
                send,
                503,
                "service-busy",
                "Service busy",
                f"{whose} limit of requests in flight is reached; retry later",
                [(b"retry-after", str(RETRY_AFTER_S).encode())],
            )
            return
        self.in_flight += 1
        self.per_client[host] = held + 1
        try:
            await self._timed(scope, receive, send)
        finally:
            self.in_flight -= 1
            left = self.per_client[host] - 1
            if left:
                self.per_client[host] = left
            else:
                del self.per_client[host]

    async def _timed(self, scope: Scope, receive: Receive, send: Send) -> None:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.body_timeout_s
        body_done = False
        timed_out = False
        started = False

        async def timed_receive() -> Message:
            nonlocal body_done, timed_out
            if body_done or timed_out:  # after the body: waiting for a disconnect, untimed
                return await receive()
            try:
                message = await asyncio.wait_for(receive(), max(deadline - loop.time(), 0.0))
            except TimeoutError:
                timed_out = True
                return {"type": "http.disconnect"}
            if message["type"] != "http.request" or not message.get("more_body", False):
                body_done = True
            return message

        async def guarded_send(message: Message) -> None:
            nonlocal started
            if timed_out:  # the 408 below answers instead
                return
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, timed_receive, guarded_send)
        except Exception:
            if not timed_out:
                raise
            logger.debug("after the body timeout", exc_info=True)
        if timed_out and not started:
            logger.warning("request body not received within %.0f s", self.body_timeout_s)
            await send_problem_and_close(
                scope,
                send,
                408,
                "request-timeout",
                "Request timeout",
                f"the request body did not arrive within {self.body_timeout_s:g} s",
                [],
            )
