"""Each reference's upload is kept in the blob store (issue "maps keep their images"): an add
writes the image's bytes as sent and its depth, a delete removes them after the row, a failed
add leaves none; on a folder and on a real S3 server, SQLite and PostgreSQL. References added
before originals were kept (a database migrated from 0007) keep serving and are listed as
lacking them."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from alembic import command
from alembic.config import Config
from fastapi.testclient import TestClient
from sqlalchemy import select

from db.blobs import BlobStore, FileBlobStore
from db.migrate import MIGRATIONS_DIR, upgrade
from db.models import ReferenceImage
from db.originals import depth_key, original_key, reconcile
from db.session import make_engine, make_session_factory
from tests.blobs.s3_server import SeaweedS3, s3_server  # noqa: F401
from tests.conftest import create_map, image_metadata, make_client, upload_view
from tools.synthetic.scene import SyntheticView, encode_depth_png, encode_png


@pytest.fixture(params=["folder", "s3"])
def blob_settings(
    request: pytest.FixtureRequest, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> dict[str, object]:
    """The settings of a store: the default folder (beside the SQLite file, or under
    SLLOC_DATA_DIR for PostgreSQL), or a bucket of the S3 server via the AWS_* variables."""
    if request.param == "folder":
        return {"data_dir": tmp_path / "data"}
    server: SeaweedS3 = request.getfixturevalue("s3_server")
    for name, value in server.env().items():
        monkeypatch.setenv(name, value)
    return {"blob_url": f"s3://{server.new_bucket()}/slloc"}


@pytest.fixture
def app_client(
    database_url: str, localizer: Any, blob_settings: dict[str, object]
) -> Iterator[TestClient]:
    with make_client(database_url, localizer, **blob_settings) as client:
        yield client


def _blobs(client: TestClient) -> BlobStore:
    blobs: BlobStore = client.app.state.blobs  # type: ignore[attr-defined]
    return blobs


def test_add_keeps_the_upload_and_delete_removes_it(
    app_client: TestClient, reference_views: list[SyntheticView]
) -> None:
    map_id = create_map(app_client)
    view = reference_views[0]
    image_bytes = encode_png(view.image)
    depth_bytes = encode_depth_png(view.depth)
    response = app_client.post(
        f"/v1/maps/{map_id}/images",
        files={
            "image": (view.name, image_bytes, "image/png"),
            "depth": ("depth.png", depth_bytes, "image/png"),
        },
        data={"metadata": json.dumps(image_metadata(view))},
    )
    assert response.status_code == 201, response.text
    image = response.json()
    sha256 = hashlib.sha256(image_bytes).hexdigest()
    assert image["has_original"] is True and image["original_sha256"] == sha256
    blobs = _blobs(app_client)
    assert blobs.get(original_key(map_id, image["id"])) == image_bytes
    assert blobs.get(depth_key(map_id, image["id"])) == depth_bytes
    original = app_client.get(f"/v1/maps/{map_id}/images/{image['id']}/original")
    assert original.status_code == 200
    assert original.content == image_bytes
    assert original.headers["content-type"] == "image/png"
    assert original.headers["etag"] == f'"{sha256}"'
    listed = app_client.get(f"/v1/maps/{map_id}/images").json()["items"]
    assert [i["has_original"] for i in listed] == [True]
    assert app_client.get(f"/v1/maps/{map_id}").json()["references_without_original"] == 0

    assert app_client.delete(f"/v1/maps/{map_id}/images/{image['id']}").status_code == 204
    assert list(blobs.list("originals/")) == []
    missing = app_client.get(f"/v1/maps/{map_id}/images/{image['id']}/original")
    assert missing.status_code == 404


def test_map_delete_removes_its_originals_and_failed_adds_leave_none(
    app_client: TestClient, reference_views: list[SyntheticView]
) -> None:
    kept = create_map(app_client, "kept")
    gone = create_map(app_client, "gone")
    for view in reference_views[:2]:
        assert upload_view(app_client, kept, view).status_code == 201  # type: ignore[attr-defined]
        assert upload_view(app_client, gone, view).status_code == 201  # type: ignore[attr-defined]
    blobs = _blobs(app_client)
    assert len(list(blobs.list("originals/"))) == 4
    # a name taken is found before any blob is written, or when the row cannot commit
    taken = upload_view(app_client, kept, reference_views[0])
    assert taken.status_code == 409  # type: ignore[attr-defined]
    bad_camera = image_metadata(reference_views[3])
    bad_camera["camera"]["width"] = 10  # type: ignore[index]
    refused = app_client.post(
        f"/v1/maps/{kept}/images",
        files={"image": ("x.png", encode_png(reference_views[3].image), "image/png")},
        data={"metadata": json.dumps(bad_camera)},
    )
    assert refused.status_code == 422
    assert app_client.delete(f"/v1/maps/{gone}").status_code == 204
    keys = {info.key for info in blobs.list("originals/")}
    assert len(keys) == 2 and all(key.startswith(f"originals/{kept}/") for key in keys)
    report = reconcile(app_client.app.state.sessions, blobs, 0.0, remove=False)  # type: ignore[attr-defined]
    assert (report.orphans, report.missing, report.rows_with_originals) == ([], [], 2)


def test_a_row_that_cannot_commit_takes_its_blobs_back(
    database_url: str,
    localizer: Any,
    localizers: Any,
    tmp_path: Path,
    reference_views: list[SyntheticView],
) -> None:
    """The add of a name another add stored while this one described the image: its blobs
    were written, its row does not commit (IntegrityError), and the blobs are deleted."""
    from app.usecases.errors import NameTakenError
    from app.usecases.images import NewImage, add_reference_image

    engine = make_engine(database_url)
    upgrade(engine)
    sessions = make_session_factory(engine)
    blobs = FileBlobStore(tmp_path / "blobs")
    with make_client(database_url, localizer, data_dir=tmp_path) as client:
        map_id = create_map(client)
    view = reference_views[0]
    new = NewImage(view.name, view.camera, view.cam_from_world)

    class StoredMeanwhile(FileBlobStore):
        """Another add of the same name commits right after this add's image blob is
        written."""

        def put(self, key: str, data: bytes) -> None:
            super().put(key, data)
            add_reference_image(sessions, localizers, map_id, new, data, blobs=blobs)

    racing = StoredMeanwhile(tmp_path / "blobs")
    with pytest.raises(NameTakenError):
        add_reference_image(sessions, localizers, map_id, new, encode_png(view.image), blobs=racing)
    report = reconcile(sessions, blobs, 0.0, remove=False)
    assert (report.orphans, report.missing, report.rows_with_originals) == ([], [], 1)
    assert report.blobs == 1
    engine.dispose()


def _alembic(engine_url: str) -> Config:
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    config.set_main_option("sqlalchemy.url", engine_url)
    return config


def test_references_added_before_originals_keep_serving(
    database_url: str,
    localizer: Any,
    tmp_path: Path,
    reference_views: list[SyntheticView],
    query_views: list[SyntheticView],
) -> None:
    """A database whose references were added at revision 0007 (no originals) and is then
    upgraded: they answer localizes from their stored features, has_original false, and the
    map counts them."""
    with make_client(database_url, localizer, data_dir=tmp_path) as client:
        map_id = create_map(client)
        for view in reference_views[:8]:
            assert upload_view(client, map_id, view).status_code == 201  # type: ignore[attr-defined]
    engine = make_engine(database_url)
    with engine.begin() as connection:  # back to the schema before this change
        config = _alembic(database_url)
        config.attributes["connection"] = connection
        command.downgrade(config, "0007")
    for path in (tmp_path / "blobs").rglob("*"):
        if path.is_file():
            path.unlink()
    upgrade(engine)
    with make_session_factory(engine)() as session:
        rows = session.scalars(select(ReferenceImage)).all()
        assert len(rows) == 8 and all(row.original_key is None for row in rows)
    engine.dispose()
    with make_client(database_url, localizer, data_dir=tmp_path) as client:
        map_out = client.get(f"/v1/maps/{map_id}").json()
        assert map_out["image_count"] == 8
        assert map_out["references_without_original"] == 8
        assert map_out["feature_models"]["servable"] is True
        images = client.get(f"/v1/maps/{map_id}/images").json()["items"]
        assert {i["has_original"] for i in images} == {False}
        assert {i["original_sha256"] for i in images} == {None}
        one = client.get(f"/v1/maps/{map_id}/images/{images[0]['id']}")
        assert one.json()["has_original"] is False
        original = client.get(f"/v1/maps/{map_id}/images/{images[0]['id']}/original")
        assert original.status_code == 404
        assert "original" in original.json()["detail"]
        response = client.post(
            f"/v1/maps/{map_id}/localize",
            files={"image": ("q.png", encode_png(query_views[0].image), "image/png")},
        )
        assert response.status_code == 200, response.text
        answer = response.json()
        assert answer.get("reason") != "no_references"
        assert answer["retrieved"], answer  # searched from the stored features
        # a new reference on the old map keeps its original
        added = upload_view(client, map_id, reference_views[9]).json()  # type: ignore[attr-defined]
        assert added["has_original"] is True
        assert client.get(f"/v1/maps/{map_id}").json()["references_without_original"] == 8
