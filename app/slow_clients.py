"""The HTTP/1.1 protocol ``slloc serve`` runs: uvicorn's, plus a request-head timeout, so
that silent and slowly-sending clients cannot hold connections."""

from __future__ import annotations

import asyncio

from uvicorn.protocols.http.h11_impl import H11Protocol

# h11's bound on a request head still being received (request line and headers), bytes
MAX_REQUEST_HEAD_BYTES = 16 * 1024


class HeadTimeoutH11Protocol(H11Protocol):
    """Closes a connection that has not sent a complete request head within
    ``timeout_keep_alive`` seconds of opening or of its last response. uvicorn alone times
    only a connection idle after a response, and stops timing at its first byte."""

    _head_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)  # type: ignore[arg-type]
        self._arm_head_timer()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._arm_head_timer()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_head_timer()
        super().connection_lost(exc)

    def _arm_head_timer(self) -> None:
        self._cancel_head_timer()
        if not self.transport.is_closing():
            self._head_timer = self.loop.call_later(self.timeout_keep_alive, self._head_timeout)

    def _cancel_head_timer(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_timeout(self) -> None:
        self._head_timer = None
        if self.cycle is None or self.cycle.response_complete:  # no request under way
            self.timeout_keep_alive_handler()
