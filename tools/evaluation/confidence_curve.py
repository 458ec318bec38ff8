"""How far the answers' confidence can be trusted: precision and recall of "accept the pose when
its confidence exceeds t" for every t.

An answer is *correct* when it has a pose within the target (by default 25 cm and 5°, the
target the shipped confidence is calibrated for). At a threshold t, the accepted answers are
those localized with confidence > t; precision is the correct fraction of them (1 when none is
accepted) and recall the fraction of the queries with ground truth answered correctly. An
image of nothing in the map has no ground truth: accepted, it is a wrong answer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.types import BoolArray, FloatArray
from tools.evaluation.metrics import QueryRecord, within

TARGET = (0.25, 5.0)
REPORTED_THRESHOLDS = (0.5, 0.8, 0.9, 0.95)


@dataclass(frozen=True)
class ConfidenceCurve:
    """Attributes:
    thresholds: (T,) increasing; the first is below every confidence (accept everything
        localized).
    precision, recall: (T,) at each threshold.
    accepted: (T,) answers accepted at each threshold.
    positives: queries with ground truth (the recall's denominator).
    """

    thresholds: FloatArray
    precision: FloatArray
    recall: FloatArray
    accepted: FloatArray
    positives: int

    def at(self, threshold: float) -> tuple[float, float, int]:
        """(precision, recall, accepted) when accepting confidence > ``threshold``."""
        i = int(np.searchsorted(self.thresholds, threshold, side="right")) - 1
        return float(self.precision[i]), float(self.recall[i]), int(self.accepted[i])


def precision_recall(
    confidence: FloatArray, correct: BoolArray, localized: BoolArray, positives: int
) -> ConfidenceCurve:
    """The curve of N answers.

    Args:
        confidence: (N,) in [0, 1].
        correct: (N,) the answer's pose is within the target.
        localized: (N,) the answer has a pose (only those are ever accepted).
        positives: queries with ground truth among the N (the recall's denominator).
    """
    conf = np.where(localized, confidence, -np.inf)
    candidates = np.unique(conf[localized])
    thresholds = np.concatenate([[-np.inf], candidates])
    accepted = conf[None, :] > thresholds[:, None]  # (T, N)
    hits = (accepted & correct[None, :]).sum(axis=1)
    count = accepted.sum(axis=1)
    precision = np.where(count > 0, hits / np.maximum(count, 1), 1.0)
    recall = hits / positives if positives else np.zeros_like(precision)
    return ConfidenceCurve(
        thresholds, precision.astype(np.float64), recall, count.astype(np.float64), positives
    )


def curve_of(records: list[QueryRecord], target: tuple[float, float] = TARGET) -> ConfidenceCurve:
    """The curve of one configuration's records."""
    max_m, max_deg = target
    correct = np.array(
        [r.localized and not r.unrelated and within(r, max_m, max_deg) for r in records],
        bool,
    )
    return precision_recall(
        np.array([r.confidence for r in records], np.float64),
        correct,
        np.array([r.localized for r in records], bool),
        sum(not r.unrelated for r in records),
    )


def curve_summary(curve: ConfidenceCurve) -> dict[str, dict[str, float]]:
    """Precision, recall and accepted answers at ``REPORTED_THRESHOLDS`` (keys ``> t``)."""
    out = {}
    for t in REPORTED_THRESHOLDS:
        precision, recall, accepted = curve.at(t)
        out[f"> {t:g}"] = {"precision": precision, "recall": recall, "accepted": accepted}
    return out
