"""Readers of posed image collections for ``slloc import``: COLMAP sparse models, kapture
datasets and CSV."""

from __future__ import annotations

import csv
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import pycolmap
from pydantic import ValidationError

from app.schemas.geo import GpsSchema
from app.schemas.geometry import CameraSchema, PoseSchema
from app.schemas.images import ImageMetadata
from services.geometry.camera import CAMERA_MODELS
from services.geometry.rigid import Rigid3d

if TYPE_CHECKING:
    import kapture

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
# optional CSV columns of a GPS position (WGS84 degrees, metres)
CSV_GPS_COLUMNS = ("latitude", "longitude", "gps_height", "gps_accuracy_m")
# kapture's GNSS sensors in WGS84 geographic coordinates (x = longitude, y = latitude)
KAPTURE_WGS84 = {"EPSG:4326", "EPSG:4979"}


@dataclass(frozen=True)
class ImportItem:
    """One image to import: its metadata, file and optional depth file."""

    metadata: ImageMetadata
    image_path: Path
    depth_path: Path | None = None


@dataclass(frozen=True)
class RejectedItem:
    """An image of the source that cannot be imported, and why (one line)."""

    name: str
    reason: str


class SourceImages(NamedTuple):
    """The images of a COLMAP model or a kapture dataset: those to import and those whose
    camera or pose is refused (each on its own: the others are imported)."""

    items: list[ImportItem]
    rejected: list[RejectedItem]


def validation_message(exc: ValidationError) -> str:
    """A pydantic validation error on one line: ``field: message`` for each error."""
    parts = []
    for error in exc.errors():
        message = error["msg"].removeprefix("Value error, ")
        where = ".".join(str(part) for part in error["loc"])
        parts.append(f"{where}: {message}" if where else message)
    return "; ".join(parts)


def read_colmap(model_dir: Path, image_dir: Path) -> SourceImages:
    """Images of a COLMAP sparse model (``cameras``/``images`` in text or binary form).

    Image names are COLMAP's (paths relative to ``image_dir``); poses are its cam_from_world.
    An image whose camera slloc refuses (a model it does not know, implausible intrinsics:
    ``check_plausible``) is rejected on its own.
    """
    reconstruction = pycolmap.Reconstruction(str(model_dir))
    items: list[ImportItem] = []
    rejected: list[RejectedItem] = []
    for image in sorted(reconstruction.images.values(), key=lambda im: im.name):
        try:
            camera = reconstruction.cameras[image.camera_id]
            _check_model(camera.model.name)
            metadata = _colmap_metadata(image.name, camera, image.cam_from_world())
        except ValidationError as exc:
            rejected.append(RejectedItem(image.name, validation_message(exc)))
            continue
        except (KeyError, ValueError) as exc:  # no such camera, a model slloc does not know
            rejected.append(RejectedItem(image.name, str(exc)))
            continue
        items.append(ImportItem(metadata, image_dir / image.name))
    return SourceImages(items, rejected)


def _check_model(name: str) -> None:
    """Raises ValueError naming the camera model when slloc does not know it."""
    if name not in CAMERA_MODELS:
        raise ValueError(
            f"camera model {name} is not supported (known: {', '.join(CAMERA_MODELS)})"
        )


def _colmap_metadata(name: str, camera: pycolmap.Camera, pose: pycolmap.Rigid3d) -> ImageMetadata:
    quat_xyzw = np.asarray(pose.rotation.quat)
    return ImageMetadata(
        name=name,
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


def read_kapture(root: Path) -> SourceImages:
    """Posed camera records of a kapture dataset (read with the ``kapture`` package: rigs
    resolved, trajectories are cam_from_world), with the GPS position of a WGS84 GNSS record
    of the same timestamp when there is one. Image names are the records' paths (relative to
    ``sensors/records_data``).

    A record whose camera slloc refuses (a model it does not know, implausible intrinsics,
    malformed parameters) is rejected on its own, and so is a record with no pose: no
    trajectory of its camera (or of the camera's rig) at its timestamp, or only a partial one
    (kapture leaves a rotation or translation blank when it is unknown, in trajectories.txt
    and in rigs.txt alike).

    Raises:
        ValueError: not a kapture dataset, or no posed camera record.
    """
    import kapture  # optional: the `kapture` extra
    from kapture.io.csv import kapture_from_dir
    from kapture.io.records import get_image_fullpath

    if not (root / "sensors" / "sensors.txt").is_file():
        raise ValueError(f"{root} is not a kapture dataset: sensors/sensors.txt is missing")
    data = kapture_from_dir(str(root))
    trajectories = data.trajectories
    if trajectories is None or data.records_camera is None or data.sensors is None:
        raise ValueError(f"{root}: a kapture dataset needs sensors, trajectories and records")
    rigs = data.rigs if data.rigs is not None else kapture.Rigs()
    # kapture cannot compose a partial pose (rigs_remove raises on it): leave those out here
    # and name them when a record needs them (_no_pose_reason)
    complete_rigs = kapture.Rigs()
    for rig_id, sensor_id, pose in kapture.flatten(rigs):
        if _is_complete(pose):
            complete_rigs[rig_id, sensor_id] = pose
    complete = kapture.Trajectories()
    for timestamp, device_id, pose in kapture.flatten(trajectories):
        if _is_complete(pose):
            complete[timestamp, device_id] = pose
    trajectories = kapture.rigs_remove(complete, complete_rigs)
    gnss_ids = {
        sensor_id
        for sensor_id, sensor in data.sensors.items()
        if sensor.sensor_type == "gnss" and set(sensor.sensor_params or ()) & KAPTURE_WGS84
    }
    items: list[ImportItem] = []
    rejected: list[RejectedItem] = []
    posed = 0
    for timestamp, sensor_id, name in kapture.flatten(data.records_camera, is_sorted=True):
        if (timestamp, sensor_id) not in trajectories:
            reason = _no_pose_reason(data.trajectories, rigs, timestamp, sensor_id)
            rejected.append(RejectedItem(name, f"no pose: {reason}"))
            continue
        posed += 1
        sensor = data.sensors.get(sensor_id)
        try:
            if sensor is None:
                raise ValueError(f"no camera sensor {sensor_id!r}")
            _check_model(sensor.camera_type.name)
            width, height, *params = (float(v) for v in sensor.camera_params)
        except (TypeError, ValueError) as exc:
            rejected.append(RejectedItem(name, f"camera {sensor_id!r} is unusable: {exc}"))
            continue
        pose = trajectories[timestamp, sensor_id]
        gps = None
        for gnss_id in gnss_ids:
            record = (data.records_gnss or {}).get(timestamp, {}).get(gnss_id)
            if record is not None:
                gps = GpsSchema(latitude=record.y, longitude=record.x, height=record.z)
                break
        try:
            metadata = ImageMetadata(
                name=name,
                camera=CameraSchema(
                    model=sensor.camera_type.name,
                    width=int(width),
                    height=int(height),
                    params=params,
                ),
                cam_from_world=PoseSchema(
                    rotation=[float(v) for v in pose.r_raw],
                    translation=[float(v) for v in pose.t_raw],
                ),
                gps=gps,
            )
        except ValidationError as exc:
            rejected.append(RejectedItem(name, validation_message(exc)))
            continue
        items.append(ImportItem(metadata, Path(get_image_fullpath(str(root), name))))
    if not posed:
        first = f" (first: {rejected[0].name}: {rejected[0].reason})" if rejected else ""
        raise ValueError(f"{root}: no camera record has a pose{first}")
    return SourceImages(items, rejected)


def _is_complete(pose: kapture.PoseTransform) -> bool:
    """Whether a kapture pose has both its rotation and its translation (either may be None:
    a blank field of trajectories.txt or rigs.txt)."""
    return not _missing_part(pose)


def _no_pose_reason(
    trajectories: kapture.Trajectories, rigs: kapture.Rigs, timestamp: int, sensor_id: str
) -> str:
    """Why the record (``timestamp``, ``sensor_id``) has no camera pose, on one line."""
    at_time = trajectories.get(timestamp, {})
    if sensor_id in at_time:  # only a partial pose, or a rig pose that left it out
        missing = _missing_part(at_time[sensor_id])
        if missing:
            return f"its trajectory at timestamp {timestamp} has no {missing}"
    rig_ids = [rig_id for rig_id, sensors in rigs.items() if sensor_id in sensors]
    for rig_id in rig_ids:
        if rig_id not in at_time:
            continue
        missing = _missing_part(at_time[rig_id])
        if missing:
            return f"the trajectory of its rig {rig_id!r} at timestamp {timestamp} has no {missing}"
        missing = _missing_part(rigs[rig_id][sensor_id])
        if missing:
            return f"its pose in rig {rig_id!r} has no {missing} (blank in rigs.txt)"
        return f"its rig {rig_id!r} has no complete pose at timestamp {timestamp}"
    rigs_named = f" nor for its rig {' / '.join(map(repr, rig_ids))}" if rig_ids else ""
    return f"trajectories.txt has nothing at timestamp {timestamp} for {sensor_id!r}{rigs_named}"


def _missing_part(pose: kapture.PoseTransform) -> str:
    """What a kapture pose lacks: "rotation", "translation", both, or "" when complete."""
    parts = [
        part
        for part, missing in (("rotation", pose.r is None), ("translation", pose.t is None))
        if missing
    ]
    return " and ".join(parts)


def read_csv(path: Path) -> list[ImportItem]:
    """Rows of ``image,camera_model,width,height,params,qw,qx,qy,qz,tx,ty,tz`` and optionally
    ``depth`` and a GPS position ``latitude,longitude[,gps_height][,gps_accuracy_m]``.

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
            gps=_csv_gps(row),
        )
    except ValidationError as exc:
        raise ValueError(f"line {line}: {validation_message(exc)}") from None
    except ValueError as exc:
        raise ValueError(f"line {line}: {exc}") from exc
    depth = row.get("depth") or None
    return ImportItem(metadata, root / row["image"], root / depth if depth else None)


def _csv_gps(row: dict[str, str]) -> GpsSchema | None:
    latitude, longitude, height, accuracy = (row.get(k) or None for k in CSV_GPS_COLUMNS)
    if latitude is None and longitude is None:
        return None
    if latitude is None or longitude is None:
        raise ValueError("a GPS position needs both latitude and longitude")
    return GpsSchema(
        latitude=float(latitude),
        longitude=float(longitude),
        height=float(height) if height else None,
        accuracy_m=float(accuracy) if accuracy else None,
    )


def iter_pending(items: list[ImportItem], existing: set[str]) -> Iterator[ImportItem]:
    """Items whose name the map does not hold yet (what makes a re-run resume)."""
    return (item for item in items if item.metadata.name not in existing)
