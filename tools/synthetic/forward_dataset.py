"""A rendered scene with forward motion, written as an import CSV with depth for ``slloc eval``:
the configuration where E5+1 and the essential-matrix family lose the position along the line
(confident wrong answers the confidence must learn to doubt).

Rows, in this order: ``FORWARD_REFERENCES`` references on the line z (every one looking
along it), ``SPREAD_REFERENCES`` references anywhere in the room, then ``FORWARD_QUERIES``
queries on the line between the references and ``SPREAD_QUERIES`` queries anywhere. Split
them with ``--references range:0-{R-1} --queries range:{R}-{R+Q-1}`` (``split_args``).
"""

from __future__ import annotations

import csv
from pathlib import Path

from tools.importers import CSV_COLUMNS
from tools.synthetic.scene import SyntheticScene, SyntheticView, encode_depth_png, encode_png

FORWARD_REFERENCES = [-5.0 + 0.75 * i for i in range(9)]
FORWARD_QUERIES = [-4.6, -3.4, -2.65, -1.9, -1.1, -0.4, 0.3, 0.7]
SPREAD_REFERENCES = 12
SPREAD_QUERIES = 8


def split_args() -> list[str]:
    """``slloc eval`` split arguments for the CSV's references and queries."""
    refs = len(FORWARD_REFERENCES) + SPREAD_REFERENCES
    queries = len(FORWARD_QUERIES) + SPREAD_QUERIES
    return [
        "--references",
        f"range:0-{refs - 1}",
        "--queries",
        f"range:{refs}-{refs + queries - 1}",
    ]


def write_forward_dataset(out: Path, seed: int = 0) -> Path:
    """Render the views into ``out`` (``images/``, ``depth/``) and write ``out/scene.csv``;
    returns the CSV's path."""
    scene = SyntheticScene(seed)
    views: list[SyntheticView] = [
        *scene.forward_views(FORWARD_REFERENCES, prefix="line-ref"),
        *scene.views(SPREAD_REFERENCES, stream=1, prefix="ref"),
        *scene.forward_views(FORWARD_QUERIES, prefix="line-query"),
        *scene.views(SPREAD_QUERIES, stream=2, prefix="query"),
    ]
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(exist_ok=True)
    path = out / "scene.csv"
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow([*CSV_COLUMNS, "depth"])
        for view in views:
            (out / "images" / view.name).write_bytes(encode_png(view.image))
            (out / "depth" / view.name).write_bytes(encode_depth_png(view.depth))
            cam, pose = view.camera, view.cam_from_world
            writer.writerow(
                [
                    f"images/{view.name}",
                    cam.model,
                    cam.width,
                    cam.height,
                    " ".join(f"{p:.17g}" for p in cam.params),
                    *(f"{v:.17g}" for v in pose.quaternion),
                    *(f"{v:.17g}" for v in pose.translation),
                    f"depth/{view.name}",
                ]
            )
    return path
