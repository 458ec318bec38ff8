"""The shipped confidence calibration: it loads, and its outputs are plausible and monotone in
the evidence for the pose."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from services.confidence.model import (
    FEATURES,
    MONOTONE_INCREASING,
    SHIPPED_CALIBRATION,
    ConfidenceModel,
    default_confidence_model,
)
from services.estimators.registry import estimator_names

STRONG = {  # a typical correct redkitchen answer (medians of the fit data)
    "num_inliers": 1500.0,
    "num_matches": 1580.0,
    "inlier_ratio": 0.95,
    "references_with_inliers": 10.0,
    "verified_points": 400.0,
    "multi_reference_tracks": 470.0,
    "inlier_area_fraction": 0.7,
    "inlier_residual_ratio": 0.08,
    "inlier_tight_fraction": 0.87,
    "radial_residual_ratio": 1.0,
}
WEAK = {  # what an unrelated image reaches
    "num_inliers": 40.0,
    "num_matches": 900.0,
    "inlier_ratio": 0.04,
    "references_with_inliers": 2.0,
    "verified_points": 10.0,
    "multi_reference_tracks": 200.0,
    "inlier_area_fraction": 0.1,
    "inlier_residual_ratio": 0.5,
    "inlier_tight_fraction": 0.2,
    "radial_residual_ratio": 2.0,
}
# a stat that is a source of each monotone feature
SOURCE = {
    "log_inliers": "num_inliers",
    "log_verified_points": "verified_points",
    "verified_fraction": "verified_points",
    "references_with_inliers": "references_with_inliers",
    "inlier_area": "inlier_area_fraction",
    "tight_inliers": "inlier_tight_fraction",
}


@pytest.fixture(scope="module")
def model() -> ConfidenceModel:
    return default_confidence_model()


def test_shipped_file_loads_and_round_trips(model: ConfidenceModel, tmp_path: Path) -> None:
    assert set(model.features) <= set(FEATURES)
    assert (model.target_position_m, model.target_rotation_deg) == (0.25, 5.0)
    model.save(tmp_path / "copy.json")
    assert ConfidenceModel.load(tmp_path / "copy.json") == model
    assert json.loads(SHIPPED_CALIBRATION.read_text())["format_version"] == 1


@pytest.mark.parametrize("estimator", estimator_names())
def test_strong_evidence_is_confident_and_weak_is_not(
    model: ConfidenceModel, estimator: str
) -> None:
    if estimator == "pose_approx":  # no correspondences: never strong evidence
        assert model.confidence({}, estimator) < 0.5
        return
    assert model.confidence(STRONG, estimator) > 0.9
    assert model.confidence(WEAK, estimator) < 0.5
    assert model.confidence({}, estimator) < 0.5


@pytest.mark.parametrize("feature", MONOTONE_INCREASING)
def test_more_evidence_never_lowers_the_confidence(model: ConfidenceModel, feature: str) -> None:
    assert model.weights[model.features.index(feature)] >= 0.0
    stat = SOURCE[feature]
    for stats in (WEAK, STRONG):
        values = [model.confidence({**stats, stat: stats[stat] * f}, "e5p1") for f in (0.5, 1, 2)]
        assert values == sorted(values), (feature, values)


def test_outputs_are_probabilities_and_auto_reads_its_choice(model: ConfidenceModel) -> None:
    for stats in (WEAK, STRONG, {}):
        for name in estimator_names():
            assert 0.0 <= model.confidence(stats, name) <= 1.0
    assert model.confidence(WEAK, "auto:local_tri_all") == model.confidence(WEAK, "local_tri_all")


def test_bad_files_are_refused(model: ConfidenceModel) -> None:
    data = model.to_json()
    with pytest.raises(ValueError, match="format"):
        ConfidenceModel.from_json({**data, "format_version": 99})
    with pytest.raises(ValueError, match="unknown confidence features"):
        ConfidenceModel.from_json({**data, "features": ["nope", *data["features"][1:]]})
    with pytest.raises(ValueError, match="length"):
        ConfidenceModel.from_json({**data, "weights": data["weights"][:-1]})
