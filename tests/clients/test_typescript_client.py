"""The TypeScript SDK (clients/typescript) against a live ``slloc serve``: its generated types
are those of openapi/openapi.json today, it builds with tsc, and test/e2e.mjs uploads the demo
references and localizes a query in Node (global fetch, FormData, Blob); the pose is checked
against the ground truth. The packages come from ``scripts/build_web.sh`` (npm ci); skipped
only where Node.js is not installed."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.clients.conftest import assert_near_truth, ground_truth
from tools.evaluation.server import LocalServer

PACKAGE = Path(__file__).resolve().parents[2] / "clients" / "typescript"

pytestmark = pytest.mark.skipif(
    shutil.which("node") is None or shutil.which("npm") is None, reason="Node.js not installed"
)


def _npm(*args: str) -> subprocess.CompletedProcess[str]:
    if not (PACKAGE / "node_modules" / ".bin" / "tsc").exists():
        pytest.fail("clients/typescript has no node_modules: run scripts/build_web.sh")
    return subprocess.run(
        ["npm", "run", "--silent", *args],
        cwd=PACKAGE,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_generated_types_are_current() -> None:
    done = _npm("check-types")
    assert done.returncode == 0, (
        "clients/typescript/src/schema.ts is stale: run `npm run generate` there\n"
        + done.stdout
        + done.stderr
    )


def test_upload_references_and_localize_the_demo_query(
    live_server: LocalServer, demo: Path
) -> None:
    built = _npm("build")
    assert built.returncode == 0, built.stdout + built.stderr
    done = subprocess.run(
        ["node", "test/e2e.mjs", live_server.url, str(demo)],
        cwd=PACKAGE,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    seen = json.loads(done.stdout.strip().splitlines()[-1])
    pose = seen["cam_from_world"]
    assert_near_truth(pose["rotation"], pose["translation"], ground_truth(demo, "query0000.png"))
    assert seen["not_found"]["status"] == 404
    assert seen["not_found"]["type"] == "https://slloc.dev/problems/not-found"
    assert seen["retry_waits"] == [1, 1, 1]
