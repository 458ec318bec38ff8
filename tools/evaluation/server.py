"""A ``slloc serve`` subprocess on a free loopback port with its own SQLite database (for
``slloc bench`` and the tests), and the peak memory of a server process."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from urllib.parse import urlparse

import httpx

LOOPBACK_HOSTS = frozenset({"127.0.0.1", "localhost", "::1"})


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def is_loopback(url: str) -> bool:
    return urlparse(url).hostname in LOOPBACK_HOSTS


def memory_mb(pid: int, field: str = "VmHWM") -> float | None:
    """A memory figure of process ``pid`` from ``/proc/<pid>/status`` in MiB: ``VmHWM`` (peak
    resident set size) or ``VmRSS`` (current); None where ``/proc`` has no such process (not
    Linux, or it ended)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(f"{field}:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def reset_peak(pid: int) -> None:
    """Resets process ``pid``'s ``VmHWM`` to its current resident size (Linux
    ``/proc/<pid>/clear_refs`` 5)."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")


class LocalServer:
    """``slloc serve`` on 127.0.0.1 and a free port, auth off, SQLite in a temporary folder;
    a context manager that waits for ``/v1/health`` and stops the process on exit."""

    def __init__(
        self,
        extra_env: dict[str, str] | None = None,
        start_timeout_s: float = 120.0,
        log_level: str = "warning",
    ):
        self._tmp = tempfile.TemporaryDirectory(prefix="slloc-server-")
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        env = {
            # the malloc arenas scripts/serve.sh and the Docker image run with, unless set
            "MALLOC_ARENA_MAX": "2",
            **os.environ,
            "SLLOC_DATABASE_URL": f"sqlite:///{self._tmp.name}/slloc.db",
            "SLLOC_API_KEYS": "",
            **(extra_env or {}),
        }
        self._log = open(Path(self._tmp.name) / "server.log", "w+b")  # noqa: SIM115
        self.process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "tools.cli",
                "serve",
                "--host",
                "127.0.0.1",
                "--port",
                str(self.port),
                "--log-level",
                log_level,
            ],
            env=env,
            stdout=self._log,
            stderr=subprocess.STDOUT,
        )
        self._wait(start_timeout_s)

    @property
    def pid(self) -> int:
        return self.process.pid

    def _wait(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                log = self.log_text()
                self.close()
                raise RuntimeError(f"slloc serve exited with {self.process.returncode}:\n{log}")
            try:
                if httpx.get(f"{self.url}/v1/health", timeout=2.0).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        log = self.log_text()
        self.close()
        raise RuntimeError(f"slloc serve did not answer on {self.url} in {timeout_s:.0f} s:\n{log}")

    def log_text(self) -> str:
        """What the server wrote to stdout and stderr so far."""
        self._log.flush()
        return (Path(self._tmp.name) / "server.log").read_text(errors="replace")

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._log.close()
        self._tmp.cleanup()

    def __enter__(self) -> LocalServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
