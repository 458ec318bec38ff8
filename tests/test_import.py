"""``slloc import``: COLMAP (text, binary, pre-4.0 text), kapture and CSV sources (GPS
included), resuming after an interrupt, and per-image failures — run through the real CLI
entry point on SQLite and PostgreSQL, checked in the database and through the HTTP API."""

from __future__ import annotations

import csv
import re
import threading
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import kapture
import numpy as np
import pycolmap
import pytest
from fastapi.testclient import TestClient
from kapture.io.csv import kapture_from_dir, kapture_to_dir
from kapture.io.records import get_image_fullpath
from sqlalchemy import inspect, select
from sqlalchemy.orm import Session

from app.main import create_app
from app.settings import Settings, get_settings
from db.arrays import from_row
from db.migrate import upgrade
from db.models import FeatureArray, Map, ReferenceImage
from db.repositories.images import ImageRepository
from db.repositories.maps import MapRepository
from db.session import make_engine
from services.estimators.registry import DEFAULT_ESTIMATOR
from services.geo.geodesy import Geodetic
from services.geo.registration import GeoRegistration
from services.geometry.rigid import Rigid3d
from services.localization.localizer import Localizer
from tools import cli
from tools.importers import read_colmap, read_kapture
from tools.synthetic.dataset import write_synthetic_dataset
from tools.synthetic.scene import SyntheticScene, SyntheticView, encode_depth_png, encode_png

NUM_VIEWS = 6
FEATURE_KINDS = {"keypoints", "descriptors", "scores", "global_descriptor"}


@pytest.fixture(scope="module")
def views(scene: SyntheticScene) -> list[SyntheticView]:
    """The first six reference views (same poses as ``reference_views[:6]``, rendered alone so
    this module stays fast when run by itself)."""
    return scene.views(NUM_VIEWS, stream=1, prefix="ref")


def _name(i: int, view: SyntheticView) -> str:
    """Image names as the map will hold them; half live in a sub-folder of the image root."""
    return f"seq{i % 2}/{view.name}"


@pytest.fixture(scope="module")
def dataset(views: list[SyntheticView], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An image root with ``seq*/ref*.png`` images and ``depth/ref*.png`` 16-bit depth maps."""
    root = tmp_path_factory.mktemp("dataset")
    for i, view in enumerate(views):
        path = root / _name(i, view)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(encode_png(view.image))
        depth = root / "depth" / view.name
        depth.parent.mkdir(exist_ok=True)
        depth.write_bytes(encode_depth_png(view.depth))
    return root


@pytest.fixture
def slloc_env(database_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """The CLI's environment: this test's database and an empty models folder."""
    models = tmp_path / "models"
    models.mkdir()
    monkeypatch.setenv("SLLOC_DATABASE_URL", database_url)
    monkeypatch.setenv("SLLOC_MODELS_DIR", str(models))
    get_settings.cache_clear()
    yield database_url
    get_settings.cache_clear()


@dataclass
class Run:
    rc: int
    out: str
    err: str

    def summary(self) -> tuple[int, int, int]:
        """(listed, stored, to add) from the first line of the import's report."""
        m = re.search(r"(\d+) images listed, (\d+) stored, (\d+) to add", self.out)
        assert m, self.out
        listed, stored, pending = (int(g) for g in m.groups())
        return listed, stored, pending


def run_import(capsys: pytest.CaptureFixture[str], *args: str | Path) -> Run:
    capsys.readouterr()
    rc = cli.main(["import", *(str(a) for a in args)])
    captured = capsys.readouterr()
    return Run(rc, captured.out, captured.err)


@dataclass
class Stored:
    images: list[ReferenceImage]
    arrays: dict[str, dict[str, FeatureArray]]  # image id -> kind -> row
    orphan_arrays: int

    def by_name(self) -> dict[str, ReferenceImage]:
        return {row.name: row for row in self.images}


def stored(database_url: str, map_name: str = "scene") -> Stored:
    """Everything the database holds for ``map_name`` (rows stay readable after closing)."""
    engine = make_engine(database_url)
    try:
        with Session(engine) as session:
            map_id = session.scalar(select(Map.id).where(Map.name == map_name))
            assert map_id is not None, f"map {map_name!r} was not created"
            images = list(
                session.scalars(select(ReferenceImage).where(ReferenceImage.map_id == map_id))
            )
            arrays: dict[str, dict[str, FeatureArray]] = {row.id: {} for row in images}
            for array in session.scalars(select(FeatureArray)):
                arrays.setdefault(array.image_id, {})[array.kind] = array
            orphans = ImageRepository(session).count_orphan_arrays()
    finally:
        engine.dispose()
    return Stored(images, arrays, orphans)


def assert_consistent(db: Stored) -> None:
    """One row per name, each with exactly its arrays, and no arrays of a missing image."""
    assert db.orphan_arrays == 0
    assert set(db.arrays) == {row.id for row in db.images}
    assert all(n == 1 for n in Counter(row.name for row in db.images).values())
    for row in db.images:
        expected = FEATURE_KINDS | ({"depth"} if row.has_depth else set())
        assert set(db.arrays[row.id]) == expected, row.name
        assert row.num_keypoints > 100
        assert from_row(db.arrays[row.id]["keypoints"]).shape[0] == row.num_keypoints


def assert_pose(
    q_wxyz: list[float] | np.ndarray, t: list[float] | np.ndarray, view: SyntheticView
) -> None:
    q = np.asarray(q_wxyz, dtype=float)
    q_true = view.cam_from_world.quaternion
    assert np.linalg.norm(q - q_true) < 1e-6 or np.linalg.norm(q + q_true) < 1e-6, (q, q_true)
    np.testing.assert_allclose(t, view.cam_from_world.translation, rtol=0, atol=1e-6)


# ---------------------------------------------------------------------------------------------
# COLMAP


def write_colmap_model(views: list[SyntheticView], out: Path, fmt: str) -> None:
    """A sparse model without points: camera 1 is PINHOLE, camera 2 the same intrinsics as
    SIMPLE_PINHOLE; odd images have the negated (equivalent) quaternion; non-contiguous ids."""
    fx, fy, cx, cy = views[0].camera.params
    assert fx == fy
    width, height = views[0].camera.width, views[0].camera.height
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(
            model="PINHOLE", width=width, height=height, params=[fx, fy, cx, cy], camera_id=1
        )
    )
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(
            model="SIMPLE_PINHOLE", width=width, height=height, params=[fx, cx, cy], camera_id=2
        )
    )
    for i, view in enumerate(views):
        w, x, y, z = view.cam_from_world.quaternion * (-1.0 if i % 2 else 1.0)
        pose = pycolmap.Rigid3d(
            pycolmap.Rotation3d(np.array([x, y, z, w])), view.cam_from_world.translation
        )
        image = pycolmap.Image(name=_name(i, view), camera_id=1 + i % 2, image_id=10 + 7 * i)
        rec.add_image_with_trivial_frame(image, pose)
    assert rec.num_reg_images() == len(views)
    out.mkdir(parents=True)
    if fmt == "binary":
        rec.write_binary(str(out))
    else:
        rec.write_text(str(out))
    if fmt == "text-3.x":  # COLMAP < 4.0 wrote no rigs/frames files
        (out / "rigs.txt").unlink()
        (out / "frames.txt").unlink()


def expected_camera(i: int, view: SyntheticView) -> tuple[str, list[float]]:
    fx, _, cx, cy = view.camera.params
    return ("PINHOLE", list(view.camera.params)) if i % 2 == 0 else ("SIMPLE_PINHOLE", [fx, cx, cy])


@pytest.mark.parametrize("fmt", ["text", "binary"])
def test_colmap_import(
    fmt: str,
    slloc_env: str,
    views: list[SyntheticView],
    dataset: Path,
    localizer: Localizer,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    model = tmp_path / "sparse" / "0"
    write_colmap_model(views, model, fmt)

    run = run_import(capsys, "--map", "scene", "--colmap", model, "--images", dataset)
    assert run.rc == 0, run.out
    assert run.summary() == (NUM_VIEWS, 0, NUM_VIEWS)
    assert f"done: {NUM_VIEWS} added, 0 failed" in run.out

    db = stored(slloc_env)
    assert_consistent(db)
    rows = db.by_name()
    assert sorted(rows) == sorted(_name(i, v) for i, v in enumerate(views))
    for i, view in enumerate(views):
        row = rows[_name(i, view)]
        model_name, params = expected_camera(i, view)
        assert (row.camera_model, row.width, row.height) == (model_name, 640, 480)
        np.testing.assert_allclose(row.camera_params, params, rtol=0, atol=1e-9)
        assert_pose([row.qw, row.qx, row.qy, row.qz], [row.tx, row.ty, row.tz], view)
        assert row.has_depth is False

    # the HTTP API sees the imported map like one built through it
    app = create_app(Settings(database_url=slloc_env), localizer=localizer)
    with TestClient(app) as client:
        maps = client.get("/v1/maps").json()["items"]
        assert [(m["name"], m["image_count"]) for m in maps] == [("scene", NUM_VIEWS)]
        # an imported map defaults like a map created through the API (once e5p1 vs auto)
        made = client.post("/v1/maps", json={"name": "through-the-api"}).json()
        assert maps[0]["default_estimator"] == made["default_estimator"] == DEFAULT_ESTIMATOR
        page = client.get(f"/v1/maps/{maps[0]['id']}/images").json()
    assert page["total"] == NUM_VIEWS
    api = {item["name"]: item for item in page["items"]}
    for i, view in enumerate(views):
        item = api[_name(i, view)]
        assert item["camera"]["model"] == expected_camera(i, view)[0]
        assert_pose(item["cam_from_world"]["rotation"], item["cam_from_world"]["translation"], view)


@pytest.mark.parametrize("fmt", ["text", "binary", "text-3.x"])
def test_read_colmap_formats(
    fmt: str, views: list[SyntheticView], dataset: Path, tmp_path: Path
) -> None:
    """The reader alone (no database): every model flavour yields the same items."""
    model = tmp_path / "model"
    write_colmap_model(views, model, fmt)
    colmap = read_colmap(model, dataset)
    assert colmap.rejected == []
    items = colmap.items
    assert [item.metadata.name for item in items] == sorted(
        _name(i, v) for i, v in enumerate(views)
    )
    by_name = {item.metadata.name: item for item in items}
    for i, view in enumerate(views):
        item = by_name[_name(i, view)]
        assert item.image_path == dataset / _name(i, view) and item.image_path.is_file()
        assert item.depth_path is None
        model_name, params = expected_camera(i, view)
        assert item.metadata.camera.model == model_name
        np.testing.assert_allclose(item.metadata.camera.params, params, rtol=0, atol=1e-9)
        pose = item.metadata.cam_from_world
        assert_pose(pose.rotation, pose.translation, view)


# ---------------------------------------------------------------------------------------------
# CSV

CSV_HEADER = [
    "image",
    "camera_model",
    "width",
    "height",
    "params",
    "qw",
    "qx",
    "qy",
    "qz",
    "tx",
    "ty",
    "tz",
    "depth",
]


def csv_row(
    image: str, view: SyntheticView, depth: str = "", width: int | None = None
) -> list[str]:
    cam = view.camera
    return [
        image,
        cam.model,
        str(width or cam.width),
        str(cam.height),
        " ".join(repr(float(p)) for p in cam.params),
        *(repr(float(v)) for v in view.cam_from_world.quaternion),
        *(repr(float(v)) for v in view.cam_from_world.translation),
        depth,
    ]


def write_csv(path: Path, rows: list[list[str]]) -> Path:
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(CSV_HEADER)
        writer.writerows(rows)
    return path


def full_csv(dataset: Path, views: list[SyntheticView], name: str = "images.csv") -> Path:
    """All views; views 0, 2, 4 come with a depth map."""
    rows = [
        csv_row(_name(i, v), v, f"depth/{v.name}" if i % 2 == 0 else "")
        for i, v in enumerate(views)
    ]
    return write_csv(dataset / name, rows)


def test_csv_import_with_depth(
    slloc_env: str,
    views: list[SyntheticView],
    dataset: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    table = full_csv(dataset, views)
    run = run_import(capsys, "--map", "scene", "--csv", table)
    assert run.rc == 0, run.out
    assert run.summary() == (NUM_VIEWS, 0, NUM_VIEWS)

    db = stored(slloc_env)
    assert_consistent(db)
    rows = db.by_name()
    assert sorted(rows) == sorted(_name(i, v) for i, v in enumerate(views))
    for i, view in enumerate(views):
        row = rows[_name(i, view)]
        assert (row.camera_model, row.width, row.height) == ("PINHOLE", 640, 480)
        assert row.camera_params == list(view.camera.params)
        assert_pose([row.qw, row.qx, row.qy, row.qz], [row.tx, row.ty, row.tz], view)
        assert row.has_depth is (i % 2 == 0)
        if row.has_depth:
            depth = from_row(db.arrays[row.id]["depth"]).astype(np.float32)
            assert depth.shape == view.depth.shape
            valid = view.depth > 0
            # millimetre PNG, stored as float16: within a few millimetres at room scale
            np.testing.assert_allclose(depth[valid], view.depth[valid], rtol=0, atol=0.01)


# ---------------------------------------------------------------------------------------------
# resuming


def test_resume_after_interrupt(
    slloc_env: str,
    views: list[SyntheticView],
    dataset: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Ctrl-C lands inside the 4th image's transaction, after its row and arrays were
    flushed; a re-run adds exactly the missing images, a third run adds nothing."""
    table = full_csv(dataset, views, "resume.csv")
    real_add = ImageRepository.add
    calls = 0

    def add_then_interrupt(self: ImageRepository, *args: object, **kwargs: object) -> object:
        nonlocal calls
        calls += 1
        row = real_add(self, *args, **kwargs)  # type: ignore[arg-type]
        if calls == 4:
            raise KeyboardInterrupt
        return row

    with monkeypatch.context() as patch:
        patch.setattr(ImageRepository, "add", add_then_interrupt)
        with pytest.raises(KeyboardInterrupt):
            cli.main(["import", "--map", "scene", "--csv", str(table)])
    first = stored(slloc_env)
    assert_consistent(first)  # the interrupted image left nothing behind
    assert len(first.images) == 3

    second = run_import(capsys, "--map", "scene", "--csv", table)
    assert second.rc == 0, second.out
    assert second.summary() == (NUM_VIEWS, 3, NUM_VIEWS - 3)
    assert f"done: {NUM_VIEWS - 3} added, 0 failed" in second.out
    db = stored(slloc_env)
    assert_consistent(db)
    assert sorted(db.by_name()) == sorted(_name(i, v) for i, v in enumerate(views))
    # the first three were not re-described or replaced
    assert {r.id for r in first.images} <= {r.id for r in db.images}

    third = run_import(capsys, "--map", "scene", "--csv", table)
    assert third.rc == 0, third.out
    assert third.summary() == (NUM_VIEWS, NUM_VIEWS, 0)
    assert "done: 0 added, 0 failed" in third.out
    again = stored(slloc_env)
    assert sorted(r.id for r in again.images) == sorted(r.id for r in db.images)


# ---------------------------------------------------------------------------------------------
# concurrent runs


def test_concurrent_imports_into_one_new_map(
    slloc_env: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Regression: two imports of one source into one new map. Both find no map and both
    create it (held at a barrier until both have looked); both list the stored names before
    either adds one, so both try every image. The loser of each race takes the winner's map
    or counts the image as stored by the other run: both exit 0, every image is stored once."""
    write_synthetic_dataset(tmp_path / "source", NUM_VIEWS, 0)
    table = tmp_path / "source" / "references.csv"
    upgrade_engine = make_engine(slloc_env)
    upgrade(upgrade_engine)  # an existing database, as the server keeps it
    upgrade_engine.dispose()
    created, listed = threading.Barrier(2, timeout=30), threading.Barrier(2, timeout=30)
    real_create, real_names = MapRepository.create, ImageRepository.names

    def create_together(self: MapRepository, *args: Any, **kwargs: Any) -> Any:
        created.wait()
        return real_create(self, *args, **kwargs)

    def names_together(self: ImageRepository, map_id: str) -> set[str]:
        names = real_names(self, map_id)
        listed.wait()
        return names

    monkeypatch.setattr(MapRepository, "create", create_together)
    monkeypatch.setattr(ImageRepository, "names", names_together)
    codes: list[int | BaseException] = []

    def run() -> None:
        try:
            codes.append(cli.main(["import", "--map", "scene", "--csv", str(table)]))
        except BaseException as exc:  # the assertion below names it
            codes.append(exc)

    capsys.readouterr()
    threads = [threading.Thread(target=run) for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(120)
    out = capsys.readouterr().out
    assert codes == [0, 0], out
    assert out.count(f"{NUM_VIEWS} images listed, 0 stored, {NUM_VIEWS} to add") == 2
    assert out.count("added (") == NUM_VIEWS
    assert out.count("exists (stored meanwhile by another run)") == NUM_VIEWS
    db = stored(slloc_env)
    assert_consistent(db)
    assert sorted(db.by_name()) == [f"references/ref{i:04d}.png" for i in range(NUM_VIEWS)]
    engine = make_engine(slloc_env)
    with Session(engine) as session:
        assert session.scalars(select(Map.name)).all() == ["scene"]
    engine.dispose()


# ---------------------------------------------------------------------------------------------
# failures


def test_failing_rows_are_reported_and_skipped(
    slloc_env: str,
    views: list[SyntheticView],
    dataset: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A missing file, corrupt bytes, a truncated PNG and a depth map of the wrong size fail
    their own row only; the command exits non-zero and the failures can be fixed and resumed."""
    root = tmp_path / "broken"
    root.mkdir()
    (root / "garbage.png").write_bytes(b"this is not an image at all")
    png = encode_png(views[2].image)
    (root / "truncated.png").write_bytes(png[: len(png) // 2])
    (root / "ok1.png").write_bytes(encode_png(views[0].image))
    (root / "ok2.png").write_bytes(encode_png(views[1].image))
    (root / "bad_depth.png").write_bytes(encode_png(views[3].image))
    (root / "small_depth.png").write_bytes(encode_depth_png(views[3].depth[::2, ::2]))
    rows = [
        csv_row("ok1.png", views[0]),
        csv_row("missing.png", views[4]),
        csv_row("garbage.png", views[5]),
        csv_row("truncated.png", views[2]),
        csv_row("bad_depth.png", views[3], depth="small_depth.png"),
        csv_row("ok2.png", views[1]),
    ]
    table = write_csv(root / "images.csv", rows)

    run = run_import(capsys, "--map", "scene", "--csv", table)
    assert run.rc != 0
    assert run.summary() == (6, 0, 6)
    failed = {
        line.split("] ", 1)[1].split(":", 1)[0] for line in run.out.splitlines() if "FAILED" in line
    }
    assert failed == {"missing.png", "garbage.png", "truncated.png", "bad_depth.png"}
    assert "done: 2 added, 4 failed" in run.out

    db = stored(slloc_env)
    assert_consistent(db)  # no feature arrays of the failed images
    assert sorted(db.by_name()) == ["ok1.png", "ok2.png"]
    ok2 = db.by_name()["ok2.png"]
    assert_pose([ok2.qw, ok2.qx, ok2.qy, ok2.qz], [ok2.tx, ok2.ty, ok2.tz], views[1])

    # fix one file and re-run: only the failed rows are retried
    (root / "missing.png").write_bytes(encode_png(views[4].image))
    rerun = run_import(capsys, "--map", "scene", "--csv", table)
    assert rerun.rc != 0
    assert rerun.summary() == (6, 2, 4)
    assert "done: 1 added, 3 failed" in rerun.out
    db = stored(slloc_env)
    assert_consistent(db)
    assert sorted(db.by_name()) == ["missing.png", "ok1.png", "ok2.png"]


def test_colmap_implausible_camera_fails_its_images_only(
    slloc_env: str,
    views: list[SyntheticView],
    dataset: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A COLMAP camera with fx = 1e-300 fails each of its images on one line naming the
    parameter; the images of the plausible camera are added and the command exits 1."""
    model = tmp_path / "sparse"
    write_colmap_model(views, model, "text")
    rec = pycolmap.Reconstruction(str(model))
    _, cx, cy = rec.cameras[2].params
    rec.cameras[2].params = [1e-300, cx, cy]
    rec.write_text(str(model))

    run = run_import(capsys, "--map", "scene", "--colmap", model, "--images", dataset)
    assert run.rc == 1, run.out + run.err
    assert run.summary() == (NUM_VIEWS, 0, NUM_VIEWS // 2)
    refused = [line for line in run.out.splitlines() if "FAILED" in line]
    assert sorted(line.split("] ", 1)[1].split(": ", 1)[0] for line in refused) == sorted(
        _name(i, v) for i, v in enumerate(views) if i % 2
    )
    for line in refused:
        assert "camera f = 1e-300 px is implausible" in line, line
    assert "Traceback" not in run.err and "validation error" not in run.out + run.err
    assert f"done: {NUM_VIEWS // 2} added, {NUM_VIEWS // 2} failed" in run.out
    assert sorted(stored(slloc_env).by_name()) == sorted(
        _name(i, v) for i, v in enumerate(views) if i % 2 == 0
    )


def test_unreadable_source_is_a_clean_error(
    slloc_env: str,
    views: list[SyntheticView],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A malformed CSV or a folder without a COLMAP model stops before touching the map."""
    bad = write_csv(tmp_path / "bad.csv", [csv_row("a.png", views[0], width=-1)])
    run = run_import(capsys, "--map", "scene", "--csv", bad)
    assert run.rc == 2, run.out
    assert "line 2" in run.err and "width" in run.err

    run = run_import(capsys, "--map", "scene", "--colmap", tmp_path / "nope", "--images", tmp_path)
    assert run.rc == 2, run.out
    assert "nope" in run.err

    run = run_import(capsys, "--map", "scene", "--csv", tmp_path / "absent.csv")
    assert run.rc == 2, run.out
    assert "absent.csv" in run.err

    engine = make_engine(slloc_env)
    try:
        with engine.connect() as conn:
            assert not inspect(conn).has_table("maps") or not conn.scalar(select(Map.id))
    finally:
        engine.dispose()


# ---------------------------------------------------------------------------------------------
# kapture, and GPS positions (CSV columns, kapture GNSS records)

GEO_ORIGIN = Geodetic(48.8584, 2.2945, 35.0)
GEO_ENU_FROM_SCENE = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
GEO_TRUTH = GeoRegistration(GEO_ORIGIN, GEO_ENU_FROM_SCENE, np.zeros(3), 1.0)


def write_kapture(views: list[SyntheticView], root: Path) -> None:
    fx, fy, cx, cy = views[0].camera.params
    sensors = kapture.Sensors()
    sensors["cam"] = kapture.Camera(kapture.CameraType.PINHOLE, [640, 480, fx, fy, cx, cy])
    sensors["gps"] = kapture.create_sensor("gnss", ["EPSG:4326"])
    trajectories = kapture.Trajectories()
    records = kapture.RecordsCamera()
    gnss = kapture.RecordsGnss()
    for timestamp, view in enumerate(views):
        name = _name(timestamp, view)
        pose = view.cam_from_world
        trajectories[timestamp, "cam"] = kapture.PoseTransform(pose.quaternion, pose.translation)
        records[timestamp, "cam"] = name
        lat, lon, h = GEO_TRUTH.geodetic_from_map(pose.center[None])[0]
        if timestamp != 0:  # the first record has no fix
            gnss[timestamp, "gps"] = kapture.RecordGnss(lon, lat, h, timestamp, 1.0)
        path = Path(get_image_fullpath(str(root), name))
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(encode_png(view.image))
    data = kapture.Kapture(
        sensors=sensors, trajectories=trajectories, records_camera=records, records_gnss=gnss
    )
    kapture_to_dir(str(root), data)


def test_kapture_import_keeps_poses_and_gps(
    slloc_env: str,
    views: list[SyntheticView],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    write_kapture(views, tmp_path / "kapture")
    run = run_import(capsys, "--map", "scene", "--kapture", tmp_path / "kapture")
    assert run.rc == 0, run.out + run.err
    assert run.summary() == (len(views), 0, len(views))
    rows = stored(slloc_env).by_name()
    for i, view in enumerate(views):
        row = rows[_name(i, view)]
        assert row.camera_params == list(view.camera.params)
        assert_pose([row.qw, row.qx, row.qy, row.qz], [row.tx, row.ty, row.tz], view)
        if i == 0:
            assert row.gps_latitude is None
            continue
        expected = GEO_TRUTH.geodetic_from_map(view.cam_from_world.center[None])[0]
        np.testing.assert_allclose(
            [row.gps_latitude, row.gps_longitude, row.gps_height], expected, atol=1e-9
        )


def test_kapture_without_poses_is_a_clean_error(
    slloc_env: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "empty" / "sensors").mkdir(parents=True)
    run = run_import(capsys, "--map", "scene", "--kapture", tmp_path / "empty")
    assert run.rc == 2 and "cannot read" in run.err


def test_csv_gps_columns(
    slloc_env: str,
    views: list[SyntheticView],
    dataset: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    table = dataset / "gps.csv"
    with table.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow([*CSV_HEADER, "latitude", "longitude", "gps_height", "gps_accuracy_m"])
        for i, view in enumerate(views):
            lat, lon, h = GEO_TRUTH.geodetic_from_map(view.cam_from_world.center[None])[0]
            writer.writerow([*csv_row(_name(i, view), view), f"{lat:.10f}", f"{lon:.10f}", h, 2.5])
    run = run_import(capsys, "--map", "scene", "--csv", table)
    assert run.rc == 0, run.out + run.err
    for row in stored(slloc_env).images:
        assert row.gps_accuracy_m == 2.5 and row.gps_latitude == pytest.approx(48.8584, abs=1e-3)


def test_kapture_bad_camera_and_missing_image_fail_their_records_only(
    slloc_env: str,
    views: list[SyntheticView],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A record of a camera slloc refuses (an UNKNOWN_CAMERA, a fisheye with fx = 1e-300)
    and a record whose image is missing fail on their own lines; a fisheye camera's
    records are added with its model; the command exits 1 and says what failed."""
    root = tmp_path / "kapture"
    write_kapture(views, root)
    data = kapture_from_dir(str(root))
    assert data.sensors is not None and data.records_camera is not None
    fx, fy, cx, cy = views[0].camera.params
    data.sensors["unknown"] = kapture.Camera(kapture.CameraType.UNKNOWN_CAMERA, [640, 480])
    data.sensors["implausible"] = kapture.Camera(
        kapture.CameraType.OPENCV_FISHEYE, [640, 480, 1e-300, fy, cx, cy, 0.0, 0.0, 0.0, 0.0]
    )
    data.sensors["fisheye"] = kapture.Camera(
        kapture.CameraType.OPENCV_FISHEYE, [640, 480, fx, fy, cx, cy, 0.0, 0.0, 0.0, 0.0]
    )
    names = {i: _name(i, view) for i, view in enumerate(views)}
    for timestamp, sensor in ((1, "unknown"), (2, "implausible"), (3, "fisheye")):
        assert data.trajectories is not None
        pose = data.trajectories[timestamp, "cam"]
        del data.trajectories[timestamp]
        del data.records_camera[timestamp]
        data.trajectories[timestamp, sensor] = pose
        data.records_camera[timestamp, sensor] = names[timestamp]
    kapture_to_dir(str(root), data)
    Path(get_image_fullpath(str(root), names[4])).unlink()

    run = run_import(capsys, "--map", "scene", "--kapture", root)
    assert run.rc == 1, run.out + run.err
    assert run.summary() == (len(views), 0, len(views) - 2)
    failed = {
        line.split("] ", 1)[1].split(": ", 1)[0]: line
        for line in run.out.splitlines()
        if "FAILED" in line
    }
    assert set(failed) == {names[1], names[2], names[4]}, run.out
    assert "UNKNOWN_CAMERA" in failed[names[1]]
    assert "camera fx = 1e-300 px is implausible" in failed[names[2]]
    assert f"done: {len(views) - 3} added, 3 failed" in run.out
    rows = stored(slloc_env).by_name()
    assert set(rows) == {names[i] for i in (0, 3, 5)}
    assert rows[names[3]].camera_model == "OPENCV_FISHEYE"


# lines of naver/kapture's samples/m1x/sensors (a rig of basler and phone cameras, lidar, wifi
# and bluetooth sensors; some camera records have no trajectory) and samples/t265/kapture/sensors
# (fisheye cameras "001"/"002" in a rig whose poses are left blank)
M1X_BASLER = "22970285"
M1X_PHONE = "AC01324954"
M1X_SENSORS = """\
# kapture format: 1.1
# sensor_id, name, sensor_type, [sensor_params]+
lidar0, vertical, lidar
22970285, basler, camera, FULL_OPENCV, 2048, 1536, 1725.842032333, 1725.842032333, 1024, 768, 0, 0, 0, 0, 0, 0, 0, 0
AC01324954, SM-G960N, camera, FULL_OPENCV, 2160, 2880, 2192.6345, 2192.6345, 1080, 1440, 0.309526634993, -1.68546591669, 0.000516016398484, 0.000304875649237, 2.77731885597, 0, 0, 0
AC01324954_wifi, SM-G960N, wifi
AC01324954_bluetooth, SM-G960N, bluetooth
"""  # noqa: E501
M1X_RIGS = """\
# kapture format: 1.1
# rig_id, sensor_id, qw, qx, qy, qz, tx, ty, tz
rig, lidar0, 2.7755575615628914e-17, -0.7071065623731627, 2.775557561562891e-17, -0.7071065623731627, -2.2204460492503132e-17, -0.4, 4.4408920985006264e-17
rig, 22970285, 0.9961943560988198, -0.08715594366579707, 5.551115123125783e-17, 0.0, 4.2106138900441864e-17, 0.7585167658481613, -0.26308222888717814
rig, AC01324954, 0.9622504041297736, -0.08418603535678781, 0.2578341082862, -0.02255800947400302, 8.64655776076572e-07, 0.8612863842075814, -0.2791071861039822
rig, AC01324954_wifi, 0.9622504041297736, -0.08418603535678781, 0.2578341082862, -0.02255800947400302, 8.64655776076572e-07, 0.8612863842075814, -0.2791071861039822
"""  # noqa: E501
M1X_TRAJECTORIES = """\
# kapture format: 1.1
# timestamp, device_id, qw, qx, qy, qz, tx, ty, tz
1555399760151000, rig, -0.03998314727387317, 0.000810622029022933, 0.9991982250752731, 0.0020501074914821946, 488.0082384493067, -8.29482066055861, 457.6611476035122
1555399760779869, rig, 0.04238353652823318, -0.0016328897188389035, -0.999100324950315, -0.0004523990708042991, 490.19333570481507, -7.546964488110166, 455.01595635993596
"""  # noqa: E501
M1X_RECORDS = """\
# kapture format: 1.1
# timestamp, device_id, image_path
1555399760151000, AC01324954, AC01324954/AC01324954_1555399760151000.jpg
1555399760779869, 22970285, 22970285/1555399760779869.jpg
1555399761168000, AC01324954, AC01324954/AC01324954_1555399761168000.jpg
1555399761779869, 22970285, 22970285/1555399761779869.jpg
"""
M1X_WIFI = """\
# kapture format: 1.1
# timestamp  , device_id      , BSSID            , frequency, RSSI, SSID          , scan_time_start, scan_time_end
1555398770307, AC01324954_wifi, 68:72:51:80:52:df, 2417     ,-33.0, M1X_PicoM2    , 0              , 0
1555398770307, AC01324955_wifi, 68:72:51:80:52:df, 2417     ,-34.0, M1X_PicoM2    , 0              , 0
"""  # noqa: E501
T265_SENSORS = """\
# kapture format: 1.1
# sensor_id, name, sensor_type, [sensor_params]+
001, , camera, OPENCV_FISHEYE, 848, 800, 284.468, 285.51, 424.355, 393.742, 0.0008, 0.031, -0.03, 0.005
002, , camera, OPENCV_FISHEYE, 848, 800, 283.999, 285.266, 417.246, 400.402, -0.002, 0.039, -0.038, 0.007
"""  # noqa: E501
T265_RIGS = """\
# kapture format: 1.1
# rig_id, sensor_id, qw, qx, qy, qz, tx, ty, tz
 rig0,   001,     ,     ,     ,     ,     ,     ,     
 rig0,   002,     ,     ,     ,     ,     ,     ,     
"""  # noqa: W291
T265_POSE = "0.9540331248716523, -0.03768128483784883, -0.2972570621910482, -0.0062565444214723875"


def write_kapture_text(root: Path, **files: str) -> Path:
    """``sensors/<name>.txt`` for each keyword argument."""
    (root / "sensors").mkdir(parents=True)
    for name, text in files.items():
        (root / "sensors" / f"{name}.txt").write_text(text)
    return root


def _kapture_rows(text: str) -> list[list[str]]:
    return [[v.strip() for v in line.split(",")] for line in text.splitlines() if line[:1] != "#"]


def test_read_kapture_m1x_rig_and_records_without_pose(tmp_path: Path) -> None:
    """m1x's metadata: FULL_OPENCV cameras of a rig (lidar, wifi and bluetooth sensors beside
    them, wifi records of a sensor it does not declare) are read with each camera's pose as
    rigs.txt ∘ trajectories.txt; the camera records whose timestamp has no trajectory are
    refused by name, saying so, instead of being left out silently."""
    root = write_kapture_text(
        tmp_path / "m1x",
        sensors=M1X_SENSORS,
        rigs=M1X_RIGS,
        trajectories=M1X_TRAJECTORIES,
        records_camera=M1X_RECORDS,
        records_wifi=M1X_WIFI,
    )
    cam_from_rig = {
        row[1]: Rigid3d.from_quaternion(np.array(row[2:6], float), np.array(row[6:], float))
        for row in _kapture_rows(M1X_RIGS)
    }
    rig_from_world = {
        int(row[0]): Rigid3d.from_quaternion(np.array(row[2:6], float), np.array(row[6:], float))
        for row in _kapture_rows(M1X_TRAJECTORIES)
    }
    source = read_kapture(root)
    expected = {
        f"{M1X_PHONE}/{M1X_PHONE}_1555399760151000.jpg": (M1X_PHONE, 1555399760151000),
        f"{M1X_BASLER}/1555399760779869.jpg": (M1X_BASLER, 1555399760779869),
    }
    assert {item.metadata.name for item in source.items} == set(expected)
    for item in source.items:
        sensor_id, timestamp = expected[item.metadata.name]
        truth = cam_from_rig[sensor_id].compose(rig_from_world[timestamp])
        pose = item.metadata.cam_from_world.to_rigid()
        np.testing.assert_allclose(pose.rotation, truth.rotation, atol=1e-9)
        np.testing.assert_allclose(pose.center, truth.center, atol=1e-9)
        assert item.metadata.camera.model == "FULL_OPENCV"
        assert len(item.metadata.camera.params) == 12
        assert item.image_path == root / "sensors" / "records_data" / item.metadata.name
    refused = {r.name: r.reason for r in source.rejected}
    assert refused == {
        f"{M1X_PHONE}/{M1X_PHONE}_1555399761168000.jpg": "no pose: trajectories.txt has "
        f"nothing at timestamp 1555399761168000 for '{M1X_PHONE}' nor for its rig 'rig'",
        f"{M1X_BASLER}/1555399761779869.jpg": "no pose: trajectories.txt has nothing at "
        f"timestamp 1555399761779869 for '{M1X_BASLER}' nor for its rig 'rig'",
    }


def test_read_kapture_t265_blank_rig_and_partial_poses(tmp_path: Path) -> None:
    """t265's rigs.txt leaves the cameras' poses in their rig blank, and kapture allows a
    trajectory without rotation or translation: a record whose pose needs such a blank is
    refused saying which (kapture.rigs_remove used to raise on them, ending the import); the
    cameras' own trajectories are read; with no posed record at all the error names why."""
    trajectories = (
        "# timestamp, device_id, qw, qx, qy, qz, tx, ty, tz\n"
        f"0, 001, {T265_POSE}, 2.7749402281860904, 0.13236653865769618, -2.868626176500939\n"
        f"1, rig0, {T265_POSE}, 2.7429402281860904, 0.13236653865769618, -2.868626176500939\n"
        "2, 001, , , , , 2.77, 0.13, -2.86\n"
    )
    records = "0, 001, leftraw/1.jpg\n1, 001, leftraw/2.jpg\n1, 002, rightraw/2.jpg\n"
    records += "2, 001, leftraw/3.jpg\n3, 002, rightraw/4.jpg\n"
    root = write_kapture_text(
        tmp_path / "t265",
        sensors=T265_SENSORS,
        rigs=T265_RIGS,
        trajectories=trajectories,
        records_camera=records,
    )
    source = read_kapture(root)
    assert [item.metadata.name for item in source.items] == ["leftraw/1.jpg"]
    camera = source.items[0].metadata.camera
    assert (camera.model, camera.width, camera.height) == ("OPENCV_FISHEYE", 848, 800)
    np.testing.assert_allclose(
        source.items[0].metadata.cam_from_world.translation,
        [2.7749402281860904, 0.13236653865769618, -2.868626176500939],
    )
    blank_rig = (
        "no pose: its pose in rig 'rig0' has no rotation and translation (blank in rigs.txt)"
    )
    assert {r.name: r.reason for r in source.rejected} == {
        "leftraw/2.jpg": blank_rig,
        "rightraw/2.jpg": blank_rig,
        "leftraw/3.jpg": "no pose: its trajectory at timestamp 2 has no rotation",
        "rightraw/4.jpg": "no pose: trajectories.txt has nothing at timestamp 3 for '002' "
        "nor for its rig 'rig0'",
    }
    (root / "sensors" / "records_camera.txt").write_text("1, 001, leftraw/2.jpg\n")
    with pytest.raises(ValueError, match=r"no camera record has a pose \(first: leftraw/2.jpg"):
        read_kapture(root)


def test_kapture_records_without_pose_are_refused_by_name(
    slloc_env: str,
    views: list[SyntheticView],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A camera record with no trajectory is counted and named in the import's report (it
    was left out silently); the posed records are added and the command exits 1."""
    root = tmp_path / "kapture"
    write_kapture(views, root)
    data = kapture_from_dir(str(root))
    assert data.trajectories is not None
    del data.trajectories[2]
    kapture_to_dir(str(root), data)
    run = run_import(capsys, "--map", "scene", "--kapture", root)
    assert run.rc == 1, run.out + run.err
    assert run.summary() == (len(views), 0, len(views) - 1)
    name = _name(2, views[2])
    assert (
        f"[refused] {name}: FAILED: no pose: trajectories.txt has nothing at timestamp 2 "
        "for 'cam'" in run.out
    ), run.out
    assert f"done: {len(views) - 1} added, 1 failed" in run.out
    assert name not in stored(slloc_env).by_name()


def test_read_colmap_every_model_and_unknown_ones(
    views: list[SyntheticView], dataset: Path, tmp_path: Path
) -> None:
    """A fisheye camera's images are read with its model; those of a model slloc does not
    know (SIMPLE_DIVISION) are refused on their own, naming it."""
    model = tmp_path / "model"
    write_colmap_model(views, model, "text")
    rec = pycolmap.Reconstruction(str(model))
    fx, fy, cx, cy = rec.cameras[1].params
    rec.cameras[1].model = pycolmap.CameraModelId.OPENCV_FISHEYE
    rec.cameras[1].params = [fx, fy, cx, cy, 0.05, -0.01, 0.0, 0.0]
    f, cx, cy = rec.cameras[2].params
    rec.cameras[2].model = pycolmap.CameraModelId.SIMPLE_DIVISION
    rec.cameras[2].params = [f, cx, cy, 0.0]
    rec.write_text(str(model))
    colmap = read_colmap(model, dataset)
    assert {item.metadata.camera.model for item in colmap.items} == {"OPENCV_FISHEYE"}
    assert len(colmap.items) == len(colmap.rejected) == NUM_VIEWS // 2
    for refused in colmap.rejected:
        assert "camera model SIMPLE_DIVISION is not supported" in refused.reason
