"""What a self-evaluation measures of one configuration, and the rule that picks the
configuration a map is best served by."""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np

# (metres, degrees): the recall thresholds reported, as the field reports them
THRESHOLDS: tuple[tuple[float, float], ...] = ((0.05, 5.0), (0.10, 10.0), (0.25, 2.0))
# an answer above this confidence should be right: within (RIGHT_M, RIGHT_DEG)
CONFIDENT = 0.8
RIGHT_M, RIGHT_DEG = 0.25, 5.0
# the recommendation: the fastest configuration whose recall at every threshold is within
# RECALL_MARGIN of the best and whose median position error is within MEDIAN_MARGIN times the
# best of those. A ratio, not millimetres: held out at radius 0, redkitchen's references measure
# xfeat-lg at 1.5 mm and sift at 1.0 mm where its queries measure 6 and 5 mm
RECALL_MARGIN = 0.05
MEDIAN_MARGIN = 1.1
# a map keeps its configuration, when it is one of those, unless the fastest is faster by more
# than this factor (latencies measured in the background vary by about as much)
LATENCY_MARGIN = 1.1


@dataclass(frozen=True)
class HeldOutAnswer:
    """One reference localized against the map without it: its errors against its stored
    pose (``inf`` when not localized)."""

    image_id: str
    name: str
    localized: bool
    reason: str | None
    position_error_m: float
    rotation_error_deg: float
    confidence: float
    num_inliers: int
    latency_ms: float
    # from its camera centre to the nearest reference it was localized against (inf: none)
    nearest_reference_m: float = math.inf

    def within(self, max_m: float, max_deg: float) -> bool:
        return self.position_error_m <= max_m and self.rotation_error_deg <= max_deg

    def as_dict(self) -> dict[str, Any]:
        return {
            "image_id": self.image_id,
            "name": self.name,
            "localized": self.localized,
            "reason": self.reason,
            "position_error_m": _finite(self.position_error_m),
            "rotation_error_deg": _finite(self.rotation_error_deg),
            "confidence": self.confidence,
            "num_inliers": self.num_inliers,
            "latency_ms": self.latency_ms,
            "nearest_reference_m": _finite(self.nearest_reference_m),
        }


def recall_key(max_m: float, max_deg: float) -> str:
    return f"{max_m * 100:g}cm_{max_deg:g}deg"


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None


def _quantile(values: list[float], q: float) -> float | None:
    """The ``q`` quantile of the errors, failures counted as infinite (None when it falls on
    one: more than ``1 - q`` of the answers failed)."""
    if not values:
        return None
    ordered = np.sort(np.asarray(values, np.float64))
    value = float(ordered[min(len(ordered) - 1, math.ceil(q * len(ordered)) - 1)])
    return _finite(value)


def summarize(answers: list[HeldOutAnswer]) -> dict[str, Any]:
    """Recall at ``THRESHOLDS``, median and p90 errors (nearest rank, failures infinite), the
    confidence's precision and recall at ``CONFIDENT``, the median latency and the failures by
    reason."""
    n = len(answers)
    right = [a for a in answers if a.within(RIGHT_M, RIGHT_DEG)]
    confident = [a for a in answers if a.localized and a.confidence > CONFIDENT]
    confident_right = [a for a in confident if a.within(RIGHT_M, RIGHT_DEG)]
    latencies = [a.latency_ms for a in answers]
    positions = [a.position_error_m for a in answers]
    rotations = [a.rotation_error_deg for a in answers]
    return {
        "held_out": n,
        "localized": sum(a.localized for a in answers),
        "recall": {
            recall_key(m, d): (sum(a.within(m, d) for a in answers) / n if n else 0.0)
            for m, d in THRESHOLDS
        },
        "position_error_m": {"median": _quantile(positions, 0.5), "p90": _quantile(positions, 0.9)},
        "rotation_error_deg": {
            "median": _quantile(rotations, 0.5),
            "p90": _quantile(rotations, 0.9),
        },
        "confidence": {
            "threshold": CONFIDENT,
            "confident": len(confident),
            # of the answers above the threshold, the share within (RIGHT_M, RIGHT_DEG)
            "precision": len(confident_right) / len(confident) if confident else None,
            # of the answers within (RIGHT_M, RIGHT_DEG), the share above the threshold
            "recall": len(confident_right) / len(right) if right else None,
        },
        "latency_ms": {"median": float(np.median(latencies)) if latencies else None},
        "nearest_reference_m": {"median": _quantile([a.nearest_reference_m for a in answers], 0.5)},
        "failures": dict(Counter(a.reason or "unknown" for a in answers if not a.localized)),
    }


def recommend(summaries: dict[str, dict[str, Any]], current: str | None = None) -> str | None:
    """The configuration a map is best served by, of those summarized: of those whose recall
    at every threshold is within ``RECALL_MARGIN`` of the best (none: those of the best mean
    recall, when each is best at another threshold), those whose median position error is
    within ``MEDIAN_MARGIN`` times the best of them, the fastest (median latency); ``current``,
    the map's configuration, while it is one of them and within ``LATENCY_MARGIN`` of the
    fastest's latency (a map does not move between configurations that measure alike); None
    when none localized anything."""
    measured = {name: s for name, s in summaries.items() if s["localized"]}
    if not measured:
        return None
    keys = [recall_key(m, d) for m, d in THRESHOLDS]
    best_recall = {k: max(s["recall"][k] for s in measured.values()) for k in keys}
    candidates = [
        name
        for name, s in measured.items()
        if all(s["recall"][k] >= best_recall[k] - RECALL_MARGIN for k in keys)
    ]
    if not candidates:
        mean = {
            name: float(np.mean([s["recall"][k] for k in keys])) for name, s in measured.items()
        }
        candidates = [name for name in measured if mean[name] == max(mean.values())]
    medians = {name: measured[name]["position_error_m"]["median"] for name in candidates}
    best_median = min((m for m in medians.values() if m is not None), default=None)
    if best_median is not None:
        candidates = [
            name
            for name in candidates
            if medians[name] is not None and medians[name] <= best_median * MEDIAN_MARGIN
        ]

    def latency(name: str) -> float:
        return float(measured[name]["latency_ms"]["median"])

    fastest = min(candidates, key=latency)
    if current in candidates and latency(current) <= LATENCY_MARGIN * latency(fastest):
        return current
    return fastest
