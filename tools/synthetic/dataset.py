"""Writes a rendered synthetic scene to disk, in the formats the API and ``slloc import`` take.

Layout of ``out``::

    references/refNNNN.png        reference images
    references/refNNNN.json       their API ``metadata`` (name, camera, cam_from_world)
    references.csv                the same, for ``slloc import --csv``
    queries/queryNNNN.png         held-out query views
    queries/queryNNNN.params.json localize ``params`` with the exact camera
    queries/ground_truth.csv      their true cam_from_world
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

from services.estimators.registry import DEFAULT_ESTIMATOR
from tools.importers import CSV_COLUMNS
from tools.synthetic.scene import SyntheticScene, SyntheticView, encode_png


def _camera(view: SyntheticView) -> dict[str, object]:
    cam = view.camera
    return {
        "model": cam.model,
        "width": cam.width,
        "height": cam.height,
        "params": list(cam.params),
    }


def _pose(view: SyntheticView) -> dict[str, list[float]]:
    return {
        "rotation": [float(v) for v in view.cam_from_world.quaternion],
        "translation": [float(v) for v in view.cam_from_world.translation],
    }


def write_synthetic_dataset(out: Path, references: int, queries: int, seed: int = 0) -> None:
    scene = SyntheticScene(seed)
    (out / "references").mkdir(parents=True, exist_ok=True)
    (out / "queries").mkdir(parents=True, exist_ok=True)
    with (out / "references.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(CSV_COLUMNS)
        for view in scene.views(references, stream=1, prefix="ref"):
            stem = view.name.removesuffix(".png")
            (out / "references" / view.name).write_bytes(encode_png(view.image))
            metadata = {"name": view.name, "camera": _camera(view), "cam_from_world": _pose(view)}
            (out / "references" / f"{stem}.json").write_text(json.dumps(metadata))
            pose = _pose(view)
            writer.writerow(
                [
                    f"references/{view.name}",
                    view.camera.model,
                    view.camera.width,
                    view.camera.height,
                    " ".join(f"{p:.17g}" for p in view.camera.params),
                    *pose["rotation"],
                    *pose["translation"],
                ]
            )
    with (out / "queries" / "ground_truth.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["image", "qw", "qx", "qy", "qz", "tx", "ty", "tz"])
        for view in scene.views(queries, stream=2, prefix="query"):
            stem = view.name.removesuffix(".png")
            (out / "queries" / view.name).write_bytes(encode_png(view.image))
            (out / "queries" / f"{stem}.params.json").write_text(
                json.dumps({"camera": _camera(view), "estimator": DEFAULT_ESTIMATOR, "top_k": 10})
            )
            pose = _pose(view)
            writer.writerow([view.name, *pose["rotation"], *pose["translation"]])
