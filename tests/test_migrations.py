"""Migrations bring a fresh database to head, and head matches the ORM models."""

from __future__ import annotations

import subprocess
import sys
import threading

from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from sqlalchemy import inspect, text

from db.base import Base
from db.migrate import upgrade
from db.session import make_engine


def test_upgrade_head_matches_models(database_url: str) -> None:
    engine = make_engine(database_url)
    upgrade(engine)
    upgrade(engine)  # idempotent
    assert {"maps", "reference_images", "feature_arrays", "alembic_version"} <= set(
        inspect(engine).get_table_names()
    )
    with engine.connect() as conn:
        diff = compare_metadata(
            MigrationContext.configure(conn, opts={"compare_type": True}), Base.metadata
        )
    engine.dispose()
    assert diff == []


# upgrades ``argv[1]`` once told to: says "ready" when imported and connected, then waits for a
# line on stdin, so the test releases every process at once
_UPGRADE_ON_GO = """
import sys
from db.migrate import upgrade
from db.session import make_engine
engine = make_engine(sys.argv[1])
engine.connect().close()
print("ready", flush=True)
sys.stdin.readline()
upgrade(engine)
"""


def test_concurrent_upgrades_of_a_fresh_database(database_url: str) -> None:
    """Two processes (two imports, two server workers) and two threads upgrade one fresh
    database at once: every one succeeds and the schema is at head once."""
    processes = [
        subprocess.Popen(
            [sys.executable, "-c", _UPGRADE_ON_GO, database_url],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(2)
    ]
    for process in processes:  # both imported and connected: neither is still starting
        assert process.stdin is not None and process.stdout is not None
        line = process.stdout.readline()
        assert line == "ready\n", line + process.communicate(timeout=120)[1]
    for process in processes:  # released together
        assert process.stdin is not None
        process.stdin.write("go\n")
        process.stdin.flush()
    for process in processes:
        _, err = process.communicate(timeout=120)
        assert process.returncode == 0, err
    engine = make_engine(database_url)
    errors: list[BaseException] = []
    together = threading.Barrier(2, timeout=60)

    def again() -> None:
        try:
            together.wait()
            upgrade(engine)
        except BaseException as exc:  # the assertion below names it
            errors.append(exc)

    threads = [threading.Thread(target=again) for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    assert errors == []
    with engine.connect() as conn:
        assert len(conn.execute(text("SELECT version_num FROM alembic_version")).all()) == 1
    engine.dispose()


def test_map_default_estimator_is_the_services() -> None:
    """A map row made without an estimator (``slloc import``, the repository) defaults like a
    map made through the API."""
    from db.models import Map
    from services.estimators.registry import DEFAULT_ESTIMATOR

    default = Map.__table__.c.default_estimator.default
    assert default is not None and getattr(default, "arg", None) == DEFAULT_ESTIMATOR


def test_maps_described_at_sifts_old_budget_keep_it(database_url: str) -> None:
    """Upgrading past SIFT's budget change pins 2048 keypoints on the maps whose references
    SIFT described at that default, and only on those: a map with a budget of its own, a map
    of another extractor and an empty map keep theirs."""
    engine = make_engine(database_url)
    upgrade(engine, "0014")
    maps = {"old_sift": None, "own_budget": 1000, "xfeat": None, "empty": None}
    described = {
        "old_sift": "sift-rootsift-2048-1024-c0.02",
        "own_budget": "sift-rootsift-1000-1024-c0.02",
        "xfeat": "xfeat-1024-640",
    }
    with engine.begin() as conn:
        for name, budget in maps.items():
            conn.execute(
                text(
                    "INSERT INTO maps (id, name, default_estimator, max_keypoints, created_at) "
                    "VALUES (:id, :id, 'auto', :budget, CURRENT_TIMESTAMP)"
                ),
                {"id": name, "budget": budget},
            )
        for name, model in described.items():
            conn.execute(
                text(
                    "INSERT INTO reference_images (id, map_id, name, camera_model, width, "
                    "height, camera_params, qw, qx, qy, qz, tx, ty, tz, num_keypoints, "
                    "has_depth, feature_model, descriptor_model, created_at) VALUES (:id, "
                    ":id, 'a.jpg', 'PINHOLE', 640, 480, '[500, 500, 320, 240]', 1, 0, 0, 0, "
                    "0, 0, 0, 100, false, :model, 'thumbnail', CURRENT_TIMESTAMP)"
                ),
                {"id": name, "model": model},
            )
    upgrade(engine)
    with engine.connect() as conn:
        budgets = dict(conn.execute(text("SELECT id, max_keypoints FROM maps")).all())
    engine.dispose()
    assert budgets == {"old_sift": 2048, "own_budget": 1000, "xfeat": None, "empty": None}
