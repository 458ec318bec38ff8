"""Shared fixtures: a synthetic scene, one localizer, and API clients on SQLite and PostgreSQL.

PostgreSQL tests use the server at ``SLLOC_TEST_POSTGRES_URL`` (default
``postgresql+psycopg://postgres@127.0.0.1:5432/postgres``); each test gets a fresh database.
"""

from __future__ import annotations

import functools
import json
import os
import uuid
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import create_engine, text
from sqlalchemy.engine import make_url

from app.main import create_app
from app.settings import Settings
from services.components import EngineConfig, Localizers, build_localizer
from services.features.configs import FEATURE_CONFIGS
from services.localization.localizer import Localizer
from services.runtime.manifest import ModelEntry, file_sha256, write_entry
from tools.synthetic.scene import SyntheticScene, SyntheticView, encode_png

POSTGRES_ADMIN_URL = os.environ.get(
    "SLLOC_TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"
)


@pytest.fixture(scope="session")
def scene() -> SyntheticScene:
    return SyntheticScene(seed=0)


@pytest.fixture(scope="session")
def reference_views(scene: SyntheticScene) -> list[SyntheticView]:
    return scene.views(24, stream=1, prefix="ref")


@pytest.fixture(scope="session")
def query_views(scene: SyntheticScene) -> list[SyntheticView]:
    return scene.views(10, stream=2, prefix="query")


def _engine_config() -> EngineConfig:
    return EngineConfig.resolve(Path("/nonexistent-models"), max_pixels=40_000_000)


@pytest.fixture(scope="session")
def localizer() -> Localizer:
    return build_localizer(_engine_config())


@pytest.fixture(scope="session")
def localizers(localizer: Localizer) -> Localizers:
    """The session's localizer as a server's only feature configuration (what the use cases
    take)."""
    return Localizers(_engine_config(), localizer)


@pytest.fixture(scope="session")
def postgres_admin_url() -> str:
    engine = create_engine(POSTGRES_ADMIN_URL)
    try:
        with engine.connect() as conn:
            conn.execute(text("SELECT 1"))
    except Exception as exc:  # pragma: no cover - CI starts the server
        pytest.fail(f"PostgreSQL is not reachable at {POSTGRES_ADMIN_URL}: {exc}")
    finally:
        engine.dispose()
    return POSTGRES_ADMIN_URL


def fresh_postgres_database(admin_url: str) -> Iterator[str]:
    name = f"slloc_test_{uuid.uuid4().hex[:12]}"
    admin = create_engine(admin_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}"'))
    try:
        yield make_url(admin_url).set(database=name).render_as_string(hide_password=False)
    finally:
        with admin.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


@pytest.fixture(params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def database_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """A fresh, empty database: a SQLite file, or a new PostgreSQL database."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'slloc.db'}"
    else:
        yield from fresh_postgres_database(request.getfixturevalue("postgres_admin_url"))


def write_model_files(models_dir: Path, *names: str) -> None:
    """Manifest entries in ``models_dir`` with intact (not loadable) files for the models of
    feature configurations ``names``: what ``auto`` reads as built."""
    for model in {m for name in names for m in FEATURE_CONFIGS[name].models}:
        path = models_dir / f"{model}.onnx"
        path.write_bytes(model.encode())
        write_entry(
            models_dir,
            ModelEntry(model, "extractor", path.name, file_sha256(path), "", "", {}, {}),
        )


def make_client(
    url: str, localizer: Localizer, raise_server_exceptions: bool = True, **settings: object
) -> TestClient:
    # maps evaluate themselves, and failed queries get a second opinion, only where a test
    # asks (tests/api/test_map_features.py, tests/api/test_second_opinion.py)
    settings.setdefault("auto_evaluation_references", 0)
    settings.setdefault("second_opinion", "")
    app = create_app(Settings(database_url=url, **settings), localizer=localizer)  # type: ignore[arg-type]
    return TestClient(app, raise_server_exceptions=raise_server_exceptions)


@pytest.fixture
def client(database_url: str, localizer: Localizer) -> Iterator[TestClient]:
    with make_client(database_url, localizer) as c:
        yield c


def image_metadata(view: SyntheticView, name: str | None = None) -> dict[str, object]:
    cam = view.camera
    return {
        "name": name or view.name,
        "camera": {
            "model": cam.model,
            "width": cam.width,
            "height": cam.height,
            "params": list(cam.params),
        },
        "cam_from_world": {
            "rotation": [float(v) for v in view.cam_from_world.quaternion],
            "translation": [float(v) for v in view.cam_from_world.translation],
        },
    }


def upload_view(
    client: TestClient, map_id: str, view: SyntheticView, name: str | None = None, **kwargs: object
) -> object:
    """POST a synthetic view as a reference image; returns the response."""
    return client.post(
        f"/v1/maps/{map_id}/images",
        files={"image": (view.name, encode_png(view.image), "image/png")},
        data={"metadata": json.dumps(image_metadata(view, name))},
        **kwargs,  # type: ignore[arg-type]
    )


def localize_view(client: TestClient, map_id: str, view: SyntheticView) -> httpx.Response:
    """POST a synthetic view as a query with its own camera; returns the response."""
    camera = view.camera
    params = {
        "camera": {
            "model": camera.model,
            "width": camera.width,
            "height": camera.height,
            "params": list(camera.params),
        }
    }
    return client.post(
        f"/v1/maps/{map_id}/localize",
        files={"image": ("q.png", encode_png(view.image), "image/png")},
        data={"params": json.dumps(params)},
    )


@functools.cache
def _another_room() -> SyntheticScene:
    return SyntheticScene(seed=7)


def seen_elsewhere(view: SyntheticView, name: str | None = None) -> SyntheticView:
    """What ``view``'s camera sees from its pose in another room (a swapped image, a query
    of another place); named ``name`` (default: the view's)."""
    image, _ = _another_room().render(view.cam_from_world)
    return SyntheticView(name or view.name, view.camera, view.cam_from_world, image, None)


def create_map(client: TestClient, name: str = "scene") -> str:
    response = client.post("/v1/maps", json={"name": name})
    assert response.status_code == 201, response.text
    return str(response.json()["id"])
