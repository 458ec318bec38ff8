"""``slloc serve`` closes connections of silent and slow clients after the keep-alive
timeout (issue #14): none may hold a connection open without finishing a request head."""

from __future__ import annotations

import socket
from collections.abc import Iterator

import pytest

from tools.evaluation.server import LocalServer

WAIT_S = 15  # bounds a hang; the server closes after 1 s


@pytest.fixture(scope="module")
def server() -> Iterator[LocalServer]:
    env = {
        "SLLOC_TIMEOUT_KEEP_ALIVE_S": "1",
        "SLLOC_FEATURES": "sift",
        "SLLOC_MODELS_DIR": "/nonexistent-models",
    }
    with LocalServer(extra_env=env) as running:
        yield running


def _closed_by_server(sock: socket.socket) -> bool:
    """Reads until the server closes (True) or ``WAIT_S`` passes (False)."""
    sock.settimeout(WAIT_S)
    try:
        while sock.recv(4096):
            pass
    except TimeoutError:
        return False
    except ConnectionResetError:
        return True
    return True


def test_silent_connection_is_closed(server: LocalServer) -> None:
    with socket.create_connection(("127.0.0.1", server.port)) as sock:
        assert _closed_by_server(sock)


def test_half_sent_request_head_is_closed(server: LocalServer) -> None:
    with socket.create_connection(("127.0.0.1", server.port)) as sock:
        sock.sendall(b"GET /v1/health HTTP/1.1\r\nHost: x\r\n")
        assert _closed_by_server(sock)


def test_idle_keep_alive_connection_is_closed(server: LocalServer) -> None:
    with socket.create_connection(("127.0.0.1", server.port)) as sock:
        sock.sendall(b"GET /v1/health HTTP/1.1\r\nHost: x\r\n\r\n")
        sock.settimeout(WAIT_S)
        assert sock.recv(4096).startswith(b"HTTP/1.1 200")
        assert _closed_by_server(sock)
