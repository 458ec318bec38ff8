"""``slloc session push`` reads an import CSV's frames: poses as ``cam_from_session``, GPS
columns as each frame's fix, in metadata the server's frame schema accepts."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from app.schemas.captures import CaptureFrameMetadata
from tools.session_push import frame_metadata, frames_from_csv
from tools.synthetic.scene import encode_png

HEADER = ["image", "camera_model", "width", "height", "params"]
HEADER += ["qw", "qx", "qy", "qz", "tx", "ty", "tz"]
GPS = ["latitude", "longitude", "gps_height", "gps_accuracy_m"]


def test_gps_columns_become_each_frames_fix(tmp_path: Path) -> None:
    image = encode_png(np.full((48, 64, 3), 128, np.uint8))
    rows = [
        ["a.png", "PINHOLE", 64, 48, "50 50 32 24", 1, 0, 0, 0, 0.0, 0.0, 0.0],
        ["b.png", "PINHOLE", 64, 48, "50 50 32 24", 1, 0, 0, 0, -0.5, 0.0, 0.0],
    ]
    fixes = [[47.3769, 8.5417, 408.5, 3.0], ["", "", "", ""]]
    with (tmp_path / "frames.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(HEADER + GPS)
        for row, fix in zip(rows, fixes, strict=True):
            (tmp_path / str(row[0])).write_bytes(image)
            writer.writerow(row + fix)
    first, second = frames_from_csv(tmp_path / "frames.csv")
    assert (first.name, second.name) == ("a.png", "b.png")
    np.testing.assert_allclose(second.cam_from_session.translation, [-0.5, 0, 0])
    sent = frame_metadata(first)
    assert sent["gps"] == {
        "latitude": 47.3769,
        "longitude": 8.5417,
        "height": 408.5,
        "accuracy_m": 3.0,
    }
    assert "gps" not in frame_metadata(second)
    parsed = CaptureFrameMetadata.model_validate(sent)
    assert parsed.gps is not None and parsed.gps.height == pytest.approx(408.5)
    assert CaptureFrameMetadata.model_validate(frame_metadata(second)).gps is None
