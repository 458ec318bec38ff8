"""What ``auto`` serves: the first of its choices whose models are built and intact, unless
the database's references were described by another of them (or by the fallback)."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.components import resolve_features
from services.features.configs import (
    AUTO,
    AUTO_CHOICES,
    FALLBACK_FEATURES,
    FEATURE_CONFIGS,
    described_by,
)
from tests.conftest import write_model_files

XFEAT_STORED = "xfeat-1024-640"
ALIKED_STORED = "aliked-n16-1024-640"
SIFT_STORED = "sift-rootsift-2048-1024-c0.02"


def test_auto_prefers_xfeat_lg_then_aliked_then_sift(tmp_path: Path) -> None:
    assert AUTO_CHOICES == ("xfeat-lg", "aliked")
    assert resolve_features(tmp_path) == FALLBACK_FEATURES == "sift"
    write_model_files(tmp_path, "aliked")
    assert resolve_features(tmp_path, AUTO) == "aliked"
    write_model_files(tmp_path, "xfeat-lg")
    assert resolve_features(tmp_path, AUTO) == "xfeat-lg"


def test_a_named_configuration_is_taken_as_is(tmp_path: Path) -> None:
    assert resolve_features(tmp_path, "disk", {ALIKED_STORED}) == "disk"


def test_an_altered_model_file_is_not_built(tmp_path: Path) -> None:
    write_model_files(tmp_path, "xfeat-lg", "aliked")
    (tmp_path / "lighterglue-xfeat.onnx").write_bytes(b"swapped")
    assert resolve_features(tmp_path) == "aliked"


@pytest.mark.parametrize(
    ("stored", "expected"),
    [
        (set(), "xfeat-lg"),
        ({ALIKED_STORED}, "aliked"),
        ({ALIKED_STORED, XFEAT_STORED}, "xfeat-lg"),
        ({SIFT_STORED}, "sift"),
        ({"disk-1024-640"}, "xfeat-lg"),  # no choice of auto's holds them: the first
    ],
)
def test_the_database_keeps_the_features_its_references_hold(
    tmp_path: Path, stored: set[str], expected: str
) -> None:
    write_model_files(tmp_path, "xfeat-lg", "aliked")
    assert resolve_features(tmp_path, AUTO, stored) == expected


def test_stored_features_of_a_preset_not_built_are_not_served(tmp_path: Path) -> None:
    write_model_files(tmp_path, "xfeat-lg")
    assert resolve_features(tmp_path, AUTO, {ALIKED_STORED}) == "xfeat-lg"


def test_described_by_reads_the_extractor_of_a_stored_name() -> None:
    assert described_by(FEATURE_CONFIGS["xfeat-lg"], XFEAT_STORED)
    assert described_by(FEATURE_CONFIGS["xfeat"], "xfeat-2048-640")
    assert not described_by(FEATURE_CONFIGS["xfeat-lg"], ALIKED_STORED)
    assert described_by(FEATURE_CONFIGS["sift"], SIFT_STORED)
    assert not described_by(FEATURE_CONFIGS["aliked"], "aliked-n32-1024-640")
