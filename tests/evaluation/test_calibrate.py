"""The confidence fit: Newton's logistic regression against known coefficients, and the
non-negative weights kept so."""

from __future__ import annotations

import numpy as np
import pytest

from tools.evaluation.calibrate import fit_logistic


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
