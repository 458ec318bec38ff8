"""The self-evaluation benchmark keeps two splits of one dataset apart: each has its own label,
hence its own row, JSON key and output folder."""

from __future__ import annotations

from pathlib import Path

from tools.benchmarks.self_evaluation import _label


def test_two_splits_of_one_dataset_have_their_own_labels(tmp_path: Path) -> None:
    folder = tmp_path / "redkitchen"
    folder.mkdir()
    (tmp_path / "kitti05").mkdir()
    frames = tmp_path / "kitti05" / "frames.csv"
    frames.write_text("")
    dense = _label(f"{folder}::range:0-499 every:5::range:500-999 every:10")
    sparse = _label(f"{folder}::range:0-499 every:10::range:500-999 every:10")
    assert _label(str(folder)) == "redkitchen"
    assert _label(str(frames)) == "kitti05"  # a CSV is named after its folder
    assert dense == "redkitchen range0-499 every5/range500-999 every10"
    assert len({_label(str(folder)), dense, sparse}) == 3
