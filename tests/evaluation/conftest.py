"""A rendered synthetic scene written as an import CSV (24 references, then 4 queries, each
with a 16-bit depth PNG), shared by the evaluation tests."""

from __future__ import annotations

import csv
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from app.settings import get_settings
from tools.evaluation.datasets import open_dataset
from tools.evaluation.split import Split, split_dataset
from tools.importers import CSV_COLUMNS
from tools.synthetic.scene import SyntheticView, encode_depth_png, encode_png

NUM_REFERENCES = 24
NUM_QUERIES = 4
SPLIT_ARGS = [
    "--references",
    f"range:0-{NUM_REFERENCES - 1}",
    "--queries",
    f"range:{NUM_REFERENCES}-{NUM_REFERENCES + NUM_QUERIES - 1}",
]


@pytest.fixture(scope="session", autouse=True)
def weight_free_features() -> Iterator[None]:
    """These tests are about the evaluation machinery: in process and in the servers they
    start, run the weight-free pipeline whether or not ONNX models are built."""
    previous = os.environ.get("SLLOC_FEATURES")
    os.environ["SLLOC_FEATURES"] = "sift"
    get_settings.cache_clear()
    yield
    if previous is None:
        del os.environ["SLLOC_FEATURES"]
    else:
        os.environ["SLLOC_FEATURES"] = previous
    get_settings.cache_clear()


def write_images(views: list[SyntheticView], root: Path) -> None:
    """``images/<name>`` PNGs and ``depth/<name>`` 16-bit depth PNGs (millimetres)."""
    (root / "images").mkdir(parents=True, exist_ok=True)
    (root / "depth").mkdir(exist_ok=True)
    for view in views:
        (root / "images" / view.name).write_bytes(encode_png(view.image))
        (root / "depth" / view.name).write_bytes(encode_depth_png(view.depth))


def write_csv(views: list[SyntheticView], path: Path) -> None:
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow([*CSV_COLUMNS, "depth"])
        for view in views:
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


@pytest.fixture(scope="session")
def eval_views(
    reference_views: list[SyntheticView], query_views: list[SyntheticView]
) -> list[SyntheticView]:
    return [*reference_views[:NUM_REFERENCES], *query_views[:NUM_QUERIES]]


@pytest.fixture(scope="session")
def synthetic_csv(
    eval_views: list[SyntheticView], tmp_path_factory: pytest.TempPathFactory
) -> Path:
    root = tmp_path_factory.mktemp("synthetic-csv")
    write_images(eval_views, root)
    write_csv(eval_views, root / "scene.csv")
    return root / "scene.csv"


@pytest.fixture(scope="session")
def split(synthetic_csv: Path) -> Split:
    """The scene's references and queries as ``slloc eval`` splits them."""
    return split_dataset(open_dataset(synthetic_csv, None), SPLIT_ARGS[1], SPLIT_ARGS[3])
