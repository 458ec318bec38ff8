"""``slloc blobs check`` reports without changing anything (exit 1 for a missing blob);
``slloc blobs sweep`` removes blobs without a row past the grace period."""

from __future__ import annotations

import os
import subprocess
import sys
import uuid
from pathlib import Path
from typing import Any

from db.blobs import FileBlobStore
from db.originals import original_key
from tests.conftest import create_map, make_client, upload_view
from tools.synthetic.scene import SyntheticView


def _slloc(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "tools.cli", "blobs", *args],
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_check_and_sweep(
    tmp_path: Path, localizer: Any, reference_views: list[SyntheticView]
) -> None:
    url = f"sqlite:///{tmp_path / 'slloc.db'}"
    with make_client(url, localizer) as client:
        map_id = create_map(client)
        ids = [upload_view(client, map_id, v).json()["id"] for v in reference_views[:2]]  # type: ignore[attr-defined]
    blobs = FileBlobStore(tmp_path / "slloc.db.blobs")
    orphan = original_key(map_id, str(uuid.uuid4()))
    blobs.put(orphan, b"left by a killed add")
    blobs.delete(original_key(map_id, ids[1]))  # removed by hand: its row is kept
    env = {"SLLOC_DATABASE_URL": url}

    check = _slloc(env, "check")
    assert check.returncode == 1, check.stderr
    assert f"without a row: {orphan}: left (check only)" in check.stdout
    assert f"missing: {original_key(map_id, ids[1])} (reference {ids[1]})" in check.stdout
    assert blobs.exists(orphan)

    young = _slloc(env, "sweep")  # the default grace period: an hour
    assert "kept (younger than the grace period)" in young.stdout
    assert blobs.exists(orphan)
    swept = _slloc(env, "sweep", "--grace-s", "0")
    assert f"without a row: {orphan}: removed" in swept.stdout
    assert not blobs.exists(orphan)
    assert swept.returncode == 1  # the missing blob is still reported
    assert blobs.exists(original_key(map_id, ids[0]))
