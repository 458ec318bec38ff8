"""Precision/recall of "accept confidence > t", on hand-made answers."""

from __future__ import annotations

import numpy as np
import pytest

from tests.evaluation.records import hand_made
from tools.evaluation.confidence_curve import curve_of, precision_recall
from tools.evaluation.metrics import QueryRecord


def test_hand_made_curve() -> None:
    # five answers to four posed queries and one unrelated image (its answer is wrong)
    confidence = np.array([0.95, 0.9, 0.85, 0.6, 0.7])
    correct = np.array([True, False, True, True, False])
    localized = np.array([True, True, True, True, True])
    curve = precision_recall(confidence, correct, localized, positives=4)
    np.testing.assert_array_equal(curve.thresholds, [-np.inf, 0.6, 0.7, 0.85, 0.9, 0.95])
    np.testing.assert_allclose(curve.precision, [3 / 5, 2 / 4, 2 / 3, 1 / 2, 1.0, 1.0])
    np.testing.assert_allclose(curve.recall, [3 / 4, 2 / 4, 2 / 4, 1 / 4, 1 / 4, 0.0])
    np.testing.assert_array_equal(curve.accepted, [5, 4, 3, 2, 1, 0])
    assert curve.at(0.8) == (2 / 3, 2 / 4, 3)  # accepts 0.95, 0.9, 0.85
    assert curve.at(0.0) == (3 / 5, 3 / 4, 5)
    assert curve.at(0.99) == (1.0, 0.0, 0)  # nothing accepted: precision 1 by convention


def test_failures_are_never_accepted() -> None:
    curve = precision_recall(
        np.array([0.0, 0.9]), np.array([False, True]), np.array([False, True]), positives=2
    )
    assert curve.at(-1.0) == (1.0, 0.5, 1)


def _record(localized: bool, pos: float, rot: float, conf: float, unrelated: bool) -> QueryRecord:
    return hand_made(pos=pos, rot=rot, localized=localized, confidence=conf, unrelated=unrelated)


@pytest.mark.parametrize("unrelated_conf", [0.5, 0.99])
def test_records_target_and_unrelated_images(unrelated_conf: float) -> None:
    records = [
        _record(True, 0.10, 1.0, 0.9, False),  # correct
        _record(True, 0.30, 1.0, 0.9, False),  # 30 cm: wrong at (25 cm, 5°)
        _record(True, 0.10, 6.0, 0.9, False),  # 6°: wrong
        _record(False, np.inf, np.inf, 0.0, False),
        _record(True, np.inf, np.inf, unrelated_conf, True),  # an accepted unrelated image
    ]
    precision, recall, accepted = curve_of(records).at(0.8)
    wrong_unrelated = unrelated_conf > 0.8
    assert accepted == 3 + wrong_unrelated
    assert precision == pytest.approx(1 / (3 + wrong_unrelated))
    assert recall == pytest.approx(1 / 4)
