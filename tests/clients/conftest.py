"""A live ``slloc serve`` and the demo scene (``slloc synth``), shared by the client tests."""

from __future__ import annotations

import csv
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from services.geometry.rigid import Rigid3d, pose_error
from tools.evaluation.server import LocalServer
from tools.synthetic.dataset import write_synthetic_dataset

#: the demo query's pose must be this close to its ground truth (the default xfeat-lg answers
#: it about 1 cm and 0.1° off; a wrong pose is metres off)
MAX_ERROR_M = 0.02
MAX_ERROR_DEG = 0.5


@pytest.fixture(scope="session")
def demo(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The README's demo scene: 24 posed references (PNG + metadata JSON), 3 queries."""
    out = tmp_path_factory.mktemp("demo")
    write_synthetic_dataset(out, references=24, queries=3, seed=0)
    return out


@pytest.fixture(scope="session")
def live_server() -> Iterator[LocalServer]:
    """``slloc serve`` on a free loopback port, SQLite in a temporary folder, auth off."""
    with LocalServer() as server:
        yield server


def ground_truth(demo: Path, image: str) -> Rigid3d:
    with (demo / "queries" / "ground_truth.csv").open() as f:
        row = next(r for r in csv.DictReader(f) if r["image"] == image)
    return Rigid3d.from_quaternion(
        np.array([float(row[k]) for k in ("qw", "qx", "qy", "qz")]),
        np.array([float(row[k]) for k in ("tx", "ty", "tz")]),
    )


def assert_near_truth(rotation: list[float], translation: list[float], truth: Rigid3d) -> None:
    estimate = Rigid3d.from_quaternion(np.array(rotation), np.array(translation))
    metres, degrees = pose_error(estimate, truth)
    assert metres < MAX_ERROR_M and degrees < MAX_ERROR_DEG, (metres, degrees)
