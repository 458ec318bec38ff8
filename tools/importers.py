"""Readers of posed image collections for ``slloc import``: COLMAP sparse models and CSV."""

from __future__ import annotations

import csv
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from app.schemas.geometry import CameraSchema, PoseSchema
from app.schemas.images import ImageMetadata
from services.geometry.rigid import Rigid3d

CSV_COLUMNS = (
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
)


@dataclass(frozen=True)
class ImportItem:
    """One image to import: its metadata, file and optional depth file."""

    metadata: ImageMetadata
    image_path: Path
    depth_path: Path | None = None


def read_colmap(model_dir: Path, image_dir: Path) -> list[ImportItem]:
    """Images of a COLMAP sparse model (``cameras``/``images`` in text or binary form).

    Image names are COLMAP's (paths relative to ``image_dir``); poses are its cam_from_world.
    """
    reconstruction = pycolmap.Reconstruction(str(model_dir))
    items = []
    for image in sorted(reconstruction.images.values(), key=lambda im: im.name):
        camera = reconstruction.cameras[image.camera_id]
        pose = image.cam_from_world()
        quat_xyzw = np.asarray(pose.rotation.quat)
        metadata = ImageMetadata(
            name=image.name,
            camera=CameraSchema(
                model=camera.model.name,
                width=camera.width,
                height=camera.height,
                params=[float(p) for p in camera.params],
            ),
            cam_from_world=PoseSchema.from_rigid(
                Rigid3d.from_quaternion(
                    np.array([quat_xyzw[3], *quat_xyzw[:3]]), np.asarray(pose.translation)
                )
            ),
        )
        items.append(ImportItem(metadata, image_dir / image.name))
    return items


def read_csv(path: Path) -> list[ImportItem]:
    """Rows of ``image,camera_model,width,height,params,qw,qx,qy,qz,tx,ty,tz[,depth]``.

    ``params`` are space-separated in COLMAP order; the pose is cam_from_world; ``image`` and
    ``depth`` paths are relative to the CSV's folder; the image name in the map is ``image``.
    """
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        missing = set(CSV_COLUMNS) - set(reader.fieldnames or ())
        if missing:
            raise ValueError(f"{path}: missing columns {sorted(missing)}; need {CSV_COLUMNS}")
        return [_csv_item(path.parent, row, line) for line, row in enumerate(reader, start=2)]


def _csv_item(root: Path, row: dict[str, str], line: int) -> ImportItem:
    try:
        metadata = ImageMetadata(
            name=row["image"],
            camera=CameraSchema(
                model=row["camera_model"],
                width=int(row["width"]),
                height=int(row["height"]),
                params=[float(v) for v in row["params"].split()],
            ),
            cam_from_world=PoseSchema(
                rotation=[float(row[k]) for k in ("qw", "qx", "qy", "qz")],
                translation=[float(row[k]) for k in ("tx", "ty", "tz")],
            ),
        )
    except ValueError as exc:
        raise ValueError(f"line {line}: {exc}") from exc
    depth = row.get("depth") or None
    return ImportItem(metadata, root / row["image"], root / depth if depth else None)


def iter_pending(items: list[ImportItem], existing: set[str]) -> Iterator[ImportItem]:
    """Items whose name the map does not hold yet (what makes a re-run resume)."""
    return (item for item in items if item.metadata.name not in existing)
