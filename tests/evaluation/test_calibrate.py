"""The confidence fit: Newton's logistic regression against known coefficients, and the
non-negative weights kept so."""

from __future__ import annotations

import numpy as np
import pytest

from tools.evaluation.calibrate import (
    Samples,
    answered_confidence,
    curve_with,
    fit_logistic,
    fit_model,
)


def _sample(weights: np.ndarray, intercept: float, n: int, seed: int) -> tuple:
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, weights.size))
    p = 1.0 / (1.0 + np.exp(-(x @ weights + intercept)))
    return x, rng.random(n) < p


def test_recovers_known_coefficients() -> None:
    truth = np.array([2.0, -1.0, 0.5])
    x, y = _sample(truth, -0.5, 40_000, seed=0)
    weights, intercept = fit_logistic(x, y, l2=1e-6)
    np.testing.assert_allclose(weights, truth, atol=0.06)
    assert abs(intercept + 0.5) < 0.06


def test_the_penalty_shrinks_weights() -> None:
    x, y = _sample(np.array([2.0, 1.0]), 0.0, 400, seed=1)
    free, _ = fit_logistic(x, y, l2=1e-6)
    shrunk, _ = fit_logistic(x, y, l2=200.0)
    assert np.all(np.abs(shrunk) < np.abs(free))


def test_nonnegative_weights_are_dropped_not_negative() -> None:
    truth = np.array([2.0, -1.0, 0.5])
    x, y = _sample(truth, 0.0, 20_000, seed=2)
    weights, intercept = fit_logistic(x, y, l2=1e-6, nonnegative=np.array([True, True, False]))
    assert weights[1] == 0.0
    # the others are the fit without the dropped feature
    kept, kept_intercept = fit_logistic(x[:, [0, 2]], y, l2=1e-6)
    np.testing.assert_allclose(weights[[0, 2]], kept, atol=1e-9)
    assert intercept == pytest.approx(kept_intercept, abs=1e-9)
    assert weights[0] > 1.0 and weights[2] > 0.2  # still the signs and rough sizes of the truth


def _samples(n: int, seed: int) -> Samples:
    """Answers whose correctness follows the pose uncertainty and the agreement of ``auto``'s
    poses; the other stats are noise."""
    rng = np.random.default_rng(seed)
    sigma = np.exp(rng.uniform(np.log(0.002), np.log(0.5), n))
    other = np.exp(rng.uniform(np.log(0.001), np.log(2.0), n))
    logit = -1.5 * np.log(sigma / 0.03) - 1.0 * np.log(other / 0.1)
    correct = rng.random(n) < 1.0 / (1.0 + np.exp(-logit))
    stats = [
        {
            "position_sigma_m": float(s),
            "auto_other_position_m": float(o),
            "auto_other_rotation_deg": 0.1,
            "num_inliers": float(rng.integers(50, 2000)),
        }
        for s, o in zip(sigma, other, strict=True)
    ]
    return Samples(
        stats,
        ["local_tri_all"] * n,
        np.ones(n, bool),
        correct,
        np.zeros(n, bool),
        np.zeros(n, bool),
        [f"q{i}" for i in range(n)],
        ["auto"] * n,
    )


def test_fit_model_on_chosen_features_learns_uncertainty_and_agreement() -> None:
    features = ("position_precision", "agreement", "log_inliers")
    model = fit_model(_samples(4000, seed=3), l2=1e-3, features=features)
    assert model.features == features
    weights = dict(zip(model.features, model.weights, strict=True))
    # both informative features get clearly positive weight, the noise next to none
    assert weights["position_precision"] > 0.5 and weights["agreement"] > 0.5
    assert abs(weights["log_inliers"]) < 0.2 * min(
        weights["position_precision"], weights["agreement"]
    )
    held_out = _samples(2000, seed=4)
    curve = curve_with(model, held_out)
    precision_fit, _, _ = curve.at(0.8)
    assert precision_fit > 0.85
    # the model's confidence tracks the frequency of correct answers
    p = np.array([model.confidence(s, "local_tri_all") for s in held_out.stats])
    for low, high in ((0.0, 0.3), (0.7, 1.0)):
        band = (p >= low) & (p < high)
        assert band.sum() > 100
        assert abs(held_out.correct[band].mean() - p[band].mean()) < 0.06


def test_answered_confidence_is_capped_by_the_uncertainty_like_the_service() -> None:
    model = fit_model(_samples(2000, seed=5), l2=1e-3, features=("position_precision", "agreement"))
    sure = {"position_sigma_m": 0.003, "rotation_sigma_deg": 0.1, "auto_other_position_m": 0.005}
    sure["auto_other_rotation_deg"] = 0.1
    assert answered_confidence(model, sure, "e5p1") == model.confidence(sure, "e5p1") > 0.9
    # 3σ above 5°: capped at 0.5, whatever the model says
    turned = {**sure, "rotation_sigma_deg": 2.0}
    assert model.confidence(turned, "e5p1") > 0.5
    assert answered_confidence(model, turned, "e5p1") == 0.5
    # an estimated focal length without an uncertainty: capped too
    assert answered_confidence(model, {"focal_px": 500.0}, "e5p1") <= 0.5
