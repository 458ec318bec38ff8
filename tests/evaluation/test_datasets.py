"""Dataset adapters (CSV, COLMAP, redkitchen layout) on synthetic scenes written by the test,
and the reference / query split rules."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from tests.evaluation.conftest import write_images
from tools.evaluation.datasets import (
    REDKITCHEN_CAMERA,
    Dataset,
    PosedImage,
    open_dataset,
)
from tools.evaluation.split import split_dataset
from tools.synthetic.scene import SyntheticView


def assert_same_poses(images: list[PosedImage], views: list[SyntheticView]) -> None:
    assert [image.name for image in images] == [view.name for view in views]
    for image, view in zip(images, views, strict=True):
        np.testing.assert_allclose(
            image.cam_from_world.matrix, view.cam_from_world.matrix, atol=1e-9
        )
        assert image.image_path.is_file()


def test_csv_adapter(synthetic_csv: Path, eval_views: list[SyntheticView]) -> None:
    dataset = open_dataset(synthetic_csv)
    assert_same_poses(
        [
            PosedImage(Path(i.name).name, i.image_path, i.camera, i.cam_from_world)
            for i in dataset.images
        ],
        eval_views,
    )
    assert all(image.camera == eval_views[0].camera for image in dataset.images)
    assert all(
        image.depth_path is not None and image.depth_path.is_file() for image in dataset.images
    )


def test_colmap_adapter(eval_views: list[SyntheticView], tmp_path: Path) -> None:
    views = eval_views[:5]
    write_images(views, tmp_path)
    fx, fy, cx, cy = views[0].camera.params
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(
            model="PINHOLE", width=640, height=480, params=[fx, fy, cx, cy], camera_id=1
        )
    )
    for i, view in enumerate(views):
        w, x, y, z = view.cam_from_world.quaternion
        pose = pycolmap.Rigid3d(
            pycolmap.Rotation3d(np.array([x, y, z, w])), view.cam_from_world.translation
        )
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=view.name, camera_id=1, image_id=1 + i), pose
        )
    (tmp_path / "sparse").mkdir()
    rec.write_binary(str(tmp_path / "sparse"))
    with pytest.raises(ValueError, match="--images"):
        open_dataset(tmp_path / "sparse")
    dataset = open_dataset(tmp_path / "sparse", tmp_path / "images")
    assert_same_poses(dataset.images, sorted(views, key=lambda v: v.name))
    assert dataset.images[0].camera == views[0].camera


def write_redkitchen(root: Path, views: list[SyntheticView], poses: str = "poses_c2w.csv") -> None:
    """``views`` in the redkitchen layout, their poses in ``root / poses``."""
    (root / "images").mkdir(exist_ok=True)
    (root / "depth").mkdir(exist_ok=True)
    with (root / poses).open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["image", *(f"T_c2w_{r}{c}" for r in range(3) for c in range(4))])
        for i, view in enumerate(views):
            name = f"frame-{i:06d}.color.jpg"
            (root / "images" / name).write_bytes(b"jpeg")
            if i % 5 == 0:
                (root / "depth" / f"frame-{i:06d}.depth.png").write_bytes(b"png")
            world_from_cam = view.cam_from_world.inverse().matrix
            writer.writerow([f"images/{name}", *(f"{v:.17g}" for v in world_from_cam.ravel())])


def test_redkitchen_adapter(eval_views: list[SyntheticView], tmp_path: Path) -> None:
    """Camera-to-world rows in, cam_from_world out; depth only where the file exists; the
    README's split as the default."""
    views = eval_views[:12]
    write_redkitchen(tmp_path, views)
    dataset = open_dataset(tmp_path)
    assert [image.name for image in dataset.images] == [
        f"frame-{i:06d}.color.jpg" for i in range(12)
    ]
    for image, view in zip(dataset.images, views, strict=True):
        np.testing.assert_allclose(
            image.cam_from_world.matrix, view.cam_from_world.matrix, atol=1e-9
        )
        assert image.camera == REDKITCHEN_CAMERA
    assert [i for i, image in enumerate(dataset.images) if image.depth_path] == [0, 5, 10]
    # default references: 0-499 every 5th (the default queries start at frame 500)
    split = split_dataset(dataset, None, "range:1-2")
    assert [image.name for image in split.references] == [
        dataset.images[i].name for i in (0, 5, 10)
    ]


def test_redkitchen_ground_truth_choice(eval_views: list[SyntheticView], tmp_path: Path) -> None:
    """The colour camera's poses (poses_c2w_sfm.csv) by default where they exist; --poses
    picks either file; a missing file or --poses on another layout is refused."""
    write_redkitchen(tmp_path, eval_views[:6])
    write_redkitchen(tmp_path, eval_views[6:12], "poses_c2w_sfm.csv")
    assert_same_poses_as(open_dataset(tmp_path).images, eval_views[6:12])
    assert_same_poses_as(open_dataset(tmp_path, poses="poses_c2w.csv").images, eval_views[:6])
    with pytest.raises(ValueError, match="no ground-truth file"):
        open_dataset(tmp_path, poses="missing.csv")
    (tmp_path / "poses_c2w_sfm.csv").unlink()
    assert_same_poses_as(open_dataset(tmp_path).images, eval_views[:6])
    with pytest.raises(ValueError, match="redkitchen-layout folder only"):
        open_dataset(tmp_path / "images", poses="poses_c2w.csv")


def assert_same_poses_as(images: list[PosedImage], views: list[SyntheticView]) -> None:
    for image, view in zip(images, views, strict=True):
        np.testing.assert_allclose(
            image.cam_from_world.matrix, view.cam_from_world.matrix, atol=1e-9
        )


def test_unknown_layout(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="not a dataset"):
        open_dataset(tmp_path)


def _dataset(count: int) -> Dataset:
    return Dataset(
        "d",
        [
            PosedImage(f"im{i:02d}", Path(f"im{i:02d}.png"), REDKITCHEN_CAMERA, None)  # type: ignore[arg-type]
            for i in range(count)
        ],
    )


@pytest.mark.parametrize(
    ("references", "queries", "expected_refs", "expected_queries"),
    [
        ("range:0-9 every:5", "range:10-19 every:3", [0, 5], [10, 13, 16, 19]),
        (None, None, [i for i in range(20) if i % 10], [0, 10]),  # generic default
        ("rest", "every:4", [i for i in range(20) if i % 4], [0, 4, 8, 12, 16]),
        ("every:2", "rest", list(range(0, 20, 2)), list(range(1, 20, 2))),
        ("all", "range:3-4", list(range(20)), [3, 4]),
    ],
)
def test_split_rules(
    references: str | None,
    queries: str | None,
    expected_refs: list[int],
    expected_queries: list[int],
) -> None:
    split = split_dataset(_dataset(20), references, queries)
    assert [image.name for image in split.references] == [f"im{i:02d}" for i in expected_refs]
    assert [image.name for image in split.queries] == [f"im{i:02d}" for i in expected_queries]


def test_split_lists(tmp_path: Path) -> None:
    (tmp_path / "refs.txt").write_text("im01\nim03\n\n")
    (tmp_path / "queries.txt").write_text("im02\n")
    split = split_dataset(
        _dataset(5), f"list:{tmp_path / 'refs.txt'}", f"list:{tmp_path / 'queries.txt'}"
    )
    assert [i.name for i in split.references] == ["im01", "im03"]
    assert [i.name for i in split.queries] == ["im02"]
    (tmp_path / "bad.txt").write_text("im99\n")
    with pytest.raises(ValueError, match="im99"):
        split_dataset(_dataset(5), f"list:{tmp_path / 'bad.txt'}", "rest")


@pytest.mark.parametrize(
    ("references", "queries", "message"),
    [
        ("rest", "rest", "only one"),
        ("every:0", "rest", "bad split token"),
        ("range:x", "rest", "bad split token"),
        ("sometimes", "rest", "bad split token"),
        ("range:0-4", "range:100-200", "0 queries"),
    ],
)
def test_split_errors(references: str, queries: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        split_dataset(_dataset(10), references, queries)
