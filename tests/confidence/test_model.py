"""The shipped confidence calibration: it loads, and its outputs are plausible and monotone in
the evidence for the pose."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from services.confidence.model import (
    AGREEMENT_CLAMP,
    FEATURES,
    MONOTONE_INCREASING,
    SHIPPED_CALIBRATION,
    ConfidenceModel,
    agreement,
    default_confidence_model,
    feature_vector,
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
    "position_sigma_m": 0.004,
    "rotation_sigma_deg": 0.15,
    "auto_other_position_m": 0.01,
    "auto_other_rotation_deg": 0.3,
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
    "position_sigma_m": 0.3,
    "rotation_sigma_deg": 4.0,
    "auto_other_position_m": 0.8,
    "auto_other_rotation_deg": 12.0,
}
# a stat that is a source of each monotone feature, and whether the feature grows with it
SOURCE = {
    "log_inliers": ("num_inliers", True),
    "log_verified_points": ("verified_points", True),
    "verified_fraction": ("verified_points", True),
    "references_with_inliers": ("references_with_inliers", True),
    "inlier_area": ("inlier_area_fraction", True),
    "tight_inliers": ("inlier_tight_fraction", True),
    "position_precision": ("position_sigma_m", False),
    "rotation_precision": ("rotation_sigma_deg", False),
    "agreement": ("auto_other_position_m", False),
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
    if feature not in model.features:
        return
    assert model.weights[model.features.index(feature)] >= 0.0
    stat, grows = SOURCE[feature]
    factors = (0.5, 1, 2) if grows else (2, 1, 0.5)
    for stats in (WEAK, STRONG):
        values = [model.confidence({**stats, stat: stats[stat] * f}, "e5p1") for f in factors]
        assert values == sorted(values), (feature, values)


def test_every_monotone_feature_has_a_source() -> None:
    assert set(SOURCE) == set(MONOTONE_INCREASING)
    for feature, (stat, grows) in SOURCE.items():
        low, high = (
            feature_vector({**STRONG, stat: STRONG[stat] * f}, [feature])[0] for f in (0.5, 2.0)
        )
        assert (high > low) == grows, feature


class TestNewFeatures:
    """The uncertainty and agreement features: their values, and what absence reads as."""

    def test_uncertainty_precision_is_minus_log_sigma_clamped(self) -> None:
        value = FEATURES["position_precision"]
        assert value({"position_sigma_m": 0.01}) == pytest.approx(-math.log(0.01))
        assert value({"position_sigma_m": 1e-9}) == pytest.approx(-math.log(1e-3))
        assert value({"position_sigma_m": 50.0}) == value({}) == pytest.approx(0.0)
        rotation = FEATURES["rotation_precision"]
        assert rotation({"rotation_sigma_deg": 0.5}) == pytest.approx(-math.log(0.5))
        assert rotation({}) == pytest.approx(-math.log(10.0))
        assert rotation({}) < rotation({"rotation_sigma_deg": 5.0})

    def test_agreement(self) -> None:
        assert agreement({}) == 0.0
        assert agreement({"auto_other_position_m": 0.01}) == 0.0  # needs both
        # 2.5 cm / 0.1°: position dominates, a tenth of the scale
        close = {"auto_other_position_m": 0.025, "auto_other_rotation_deg": 0.1}
        assert agreement(close) == pytest.approx(math.log(10.0))
        # 5 cm / 2.5°: the rotation, half its scale, dominates
        turned = {"auto_other_position_m": 0.05, "auto_other_rotation_deg": 2.5}
        assert agreement(turned) == pytest.approx(math.log(2.0))
        far = {"auto_other_position_m": 2.5, "auto_other_rotation_deg": 1.0}
        assert agreement(far) == pytest.approx(-math.log(10.0))
        same = {"auto_other_position_m": 0.0, "auto_other_rotation_deg": 0.0}
        assert agreement(same) == AGREEMENT_CLAMP
        assert agreement({**far, "auto_other_position_m": 1e6}) == -AGREEMENT_CLAMP


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
