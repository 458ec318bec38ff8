"""``auto`` on a database that already holds references: the server keeps serving the features
they were described with (SQLite and PostgreSQL)."""

from __future__ import annotations

from pathlib import Path

from fastapi.testclient import TestClient

from app.engine_config import engine_config
from app.settings import Settings
from db.session import make_engine, make_session_factory
from services.features.configs import AUTO
from tests.conftest import create_map, upload_view, write_model_files
from tools.synthetic.scene import SyntheticView


def _served(database_url: str, models_dir: Path, features: str = AUTO) -> str:
    engine = make_engine(database_url)
    try:
        settings = Settings(database_url=database_url, models_dir=models_dir, features=features)
        return engine_config(settings, make_session_factory(engine)).features
    finally:
        engine.dispose()


def test_auto_keeps_the_features_of_the_stored_references(
    client: TestClient, database_url: str, reference_views: list[SyntheticView], tmp_path: Path
) -> None:
    write_model_files(tmp_path, "xfeat-lg")
    assert _served(database_url, tmp_path) == "xfeat-lg"  # no references yet
    map_id = create_map(client)
    assert upload_view(client, map_id, reference_views[0]).status_code == 201  # type: ignore[attr-defined]
    assert _served(database_url, tmp_path) == "sift"  # the client's localizer described it


def test_a_named_configuration_ignores_the_stored_references(
    client: TestClient, database_url: str, reference_views: list[SyntheticView], tmp_path: Path
) -> None:
    map_id = create_map(client)
    assert upload_view(client, map_id, reference_views[0]).status_code == 201  # type: ignore[attr-defined]
    assert _served(database_url, tmp_path, "xfeat") == "xfeat"
