"""Dataset adapters: posed images (image file, camera, ground-truth pose, optional depth) from a
COLMAP model + image folder, an import CSV, or the redkitchen (7-Scenes) layout.

Poses are ``cam_from_world``; cameras are COLMAP's (pixel centre convention (0.5, 0.5)).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.geometry.camera import Camera
from services.geometry.rigid import Rigid3d
from tools.importers import ImportItem, read_colmap, read_csv

# redkitchen: fx = fy = 525, cx = 320, cy = 240 fit the colour frames (dataset README)
REDKITCHEN_CAMERA = Camera("PINHOLE", 640, 480, (525.0, 525.0, 320.0, 240.0))


@dataclass(frozen=True)
class PosedImage:
    """One image of a dataset with its ground truth."""

    name: str
    image_path: Path
    camera: Camera
    cam_from_world: Rigid3d
    depth_path: Path | None = None


@dataclass(frozen=True)
class Dataset:
    """Posed images in dataset order (split rules index into it) and the split the dataset
    suggests (``None`` = the generic default)."""

    name: str
    images: list[PosedImage]
    default_references: str | None = None
    default_queries: str | None = None


def _from_items(items: list[ImportItem]) -> list[PosedImage]:
    return [
        PosedImage(
            item.metadata.name,
            item.image_path,
            item.metadata.camera.to_camera(),
            item.metadata.cam_from_world.to_rigid(),
            item.depth_path,
        )
        for item in items
    ]


def colmap_dataset(model_dir: Path, image_dir: Path) -> Dataset:
    """A COLMAP sparse model (text or binary), images sorted by name.

    Raises:
        ValueError: an image's camera is implausible (its ground truth cannot be trusted).
    """
    colmap = read_colmap(model_dir, image_dir)
    if colmap.rejected:
        first = colmap.rejected[0]
        raise ValueError(
            f"{model_dir}: {len(colmap.rejected)} images refused, "
            f"first {first.name}: {first.reason}"
        )
    return Dataset(model_dir.name, _from_items(colmap.items))


def csv_dataset(path: Path) -> Dataset:
    """An import CSV (``image,camera_model,width,height,params,qw,…,tz[,depth]``), row order."""
    return Dataset(path.stem, _from_items(read_csv(path)))


REDKITCHEN_POSES = "poses_c2w.csv"  # the depth camera's track (KinectFusion)
# the colour camera's Structure-from-Motion poses: the ground truth to tune and compare on
# (``poses_c2w.csv`` sits 2.2° and 6 cm off the colour camera)
REDKITCHEN_SFM_POSES = "poses_c2w_sfm.csv"


def redkitchen_dataset(root: Path, poses: str | None = None) -> Dataset:
    """The redkitchen layout: ``images/frame-NNNNNN.color.jpg``, ``depth/frame-NNNNNN.depth.png``
    (every 5th frame) and camera-to-world 3×4 rows, frames in order, from ``poses`` (a file
    name in ``root``; default: ``poses_c2w_sfm.csv`` where it exists, else ``poses_c2w.csv``).

    Raises:
        ValueError: ``poses`` names no file in ``root``.
    """
    if poses is None:
        poses = (
            REDKITCHEN_SFM_POSES if (root / REDKITCHEN_SFM_POSES).is_file() else REDKITCHEN_POSES
        )
    if not (root / poses).is_file():
        raise ValueError(f"{root}: no ground-truth file {poses!r}")
    images = []
    with (root / poses).open(newline="") as f:
        for row in csv.DictReader(f):
            name = Path(row["image"]).name
            m = np.array([float(row[f"T_c2w_{r}{c}"]) for r in range(3) for c in range(4)])
            m = m.reshape(3, 4)
            # KinectFusion rotations are orthonormal only to ~1e-7; re-orthonormalise.
            u, _, vt = np.linalg.svd(m[:, :3])
            cam_from_world = Rigid3d(u @ vt, m[:, 3]).inverse()
            depth = root / "depth" / name.replace(".color.jpg", ".depth.png")
            images.append(
                PosedImage(
                    name,
                    root / "images" / name,
                    REDKITCHEN_CAMERA,
                    cam_from_world,
                    depth if depth.exists() else None,
                )
            )
    images.sort(key=lambda image: image.name)
    # the README's split: references 0…499 every 5th, queries 500…999 every 10th
    return Dataset(root.name, images, "range:0-499 every:5", "range:500-999 every:10")


def open_dataset(path: Path, images: Path | None = None, poses: str | None = None) -> Dataset:
    """The adapter by layout: a ``.csv`` file; a folder with ``poses_c2w.csv`` (redkitchen,
    its ground truth from ``poses``, see ``redkitchen_dataset``); a COLMAP model folder
    (``cameras.txt``/``cameras.bin``, needs ``images``).

    Raises:
        ValueError: the layout is not recognised, a COLMAP model comes without ``images``, or
            ``poses`` is given for another layout than redkitchen's.
    """
    if poses is not None and not (path / REDKITCHEN_POSES).is_file():
        raise ValueError(f"{path}: --poses applies to a redkitchen-layout folder only")
    if path.is_file() and path.suffix.lower() == ".csv":
        return csv_dataset(path)
    if (path / REDKITCHEN_POSES).is_file():
        return redkitchen_dataset(path, poses)
    if (path / "cameras.txt").is_file() or (path / "cameras.bin").is_file():
        if images is None:
            raise ValueError(f"{path} is a COLMAP model: give its image folder with --images")
        return colmap_dataset(path, images)
    raise ValueError(
        f"{path}: not a dataset (expected an import .csv, a redkitchen folder with "
        "poses_c2w.csv, or a COLMAP model folder)"
    )
