"""The confidence of a localization: a logistic model over features of the result, fitted on
evaluation data (``slloc calibrate``) and stored as a small versioned JSON file of
coefficients.

``confidence = σ(b + b_estimator + Σ w_j · (f_j − mean_j) / scale_j)`` estimates the
probability that the pose lies within the file's target (25 cm and 5° as shipped). The
features ``f_j`` come from the result's stats (see ``feature_vector``); a stat the result lacks
counts as 0, an estimator the file does not know gets no offset, and ``auto:<name>`` is read
as ``<name>``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from services.types import FloatArray

FORMAT_VERSION = 1
SHIPPED_CALIBRATION = Path(__file__).with_name("calibration.json")


def _log1p(stats: Mapping[str, float], key: str) -> float:
    return math.log1p(max(stats.get(key, 0.0), 0.0))


def _ratio(stats: Mapping[str, float], num: str, den: str) -> float:
    return stats.get(num, 0.0) / max(stats.get(den, 0.0), 1.0)


# the pose uncertainty's clamps (``services.estimators.uncertainty``; no uncertainty reads as the
# largest); map units and degrees
POSITION_SIGMA_RANGE_M = (1e-3, 1.0)
ROTATION_SIGMA_RANGE_DEG = (1e-2, 10.0)
# the scale of disagreement between ``auto``'s verified poses at which agreement reads 0 (no
# evidence either way), and the clamp of its log
AGREEMENT_SCALE = (0.25, 5.0)
AGREEMENT_CLAMP = 3.0


def _precision(stats: Mapping[str, float], key: str, bounds: tuple[float, float]) -> float:
    """−log of the stat clamped to ``bounds`` (absent: the upper bound)."""
    low, high = bounds
    return -math.log(min(max(stats.get(key, high), low), high))


def agreement(stats: Mapping[str, float]) -> float:
    """How well the other verified poses of ``auto`` agree with its answer:
    ``−log max(Δposition / 0.25, Δrotation / 5°)`` clamped to ±3 — positive when they lie
    closer than 25 cm and 5°, negative farther — and 0 without another pose (another
    estimator, or only one of ``auto``'s verified)."""
    if "auto_other_position_m" not in stats or "auto_other_rotation_deg" not in stats:
        return 0.0
    ratio = max(
        stats["auto_other_position_m"] / AGREEMENT_SCALE[0],
        stats["auto_other_rotation_deg"] / AGREEMENT_SCALE[1],
        1e-12,
    )
    return min(max(-math.log(ratio), -AGREEMENT_CLAMP), AGREEMENT_CLAMP)


# name → how it is computed from the stats of a result; each grows with the evidence for the
# pose except ``residual`` (the inliers' median error over the inlier threshold) and
# ``radial_residual`` (log of how much larger the errors are far from the principal point)
FEATURES: dict[str, Callable[[Mapping[str, float]], float]] = {
    "log_inliers": lambda s: _log1p(s, "num_inliers"),
    "log_verified_points": lambda s: _log1p(s, "verified_points"),
    "verified_fraction": lambda s: _ratio(s, "verified_points", "multi_reference_tracks"),
    "references_with_inliers": lambda s: min(s.get("references_with_inliers", 0.0), 10.0),
    "inlier_ratio": lambda s: s.get("inlier_ratio", 0.0),
    "inlier_area": lambda s: s.get("inlier_area_fraction", 0.0),
    "residual": lambda s: s.get("inlier_residual_ratio", 0.0),
    "tight_inliers": lambda s: s.get("inlier_tight_fraction", 0.0),
    "radial_residual": lambda s: math.log(max(s.get("radial_residual_ratio", 1.0), 1e-3)),
    # −log of the pose's predicted RMS position / rotation error (``position_sigma_m``,
    # ``rotation_sigma_deg``); no uncertainty reads as the largest
    "position_precision": lambda s: _precision(s, "position_sigma_m", POSITION_SIGMA_RANGE_M),
    "rotation_precision": lambda s: _precision(s, "rotation_sigma_deg", ROTATION_SIGMA_RANGE_DEG),
    "agreement": agreement,
}
# features whose weight the fit keeps >= 0: more of them never lowers the confidence
MONOTONE_INCREASING = (
    "log_inliers",
    "log_verified_points",
    "verified_fraction",
    "references_with_inliers",
    "inlier_area",
    "tight_inliers",
    "position_precision",
    "rotation_precision",
    "agreement",
)


def feature_vector(stats: Mapping[str, float], names: Sequence[str]) -> FloatArray:
    """(F,) float64 features ``names`` (keys of ``FEATURES``) of a result's stats."""
    return np.array([float(FEATURES[name](stats)) for name in names], np.float64)


def base_estimator(name: str) -> str:
    """``auto:local_tri_all`` → ``local_tri_all``; other names unchanged."""
    return name.rsplit(":", 1)[-1]


@dataclass(frozen=True)
class ConfidenceModel:
    """Logistic-regression coefficients (see the module docstring).

    Attributes:
        features: names of the features, keys of ``FEATURES``.
        mean, scale: (F,) standardisation of each feature.
        weights: (F,) weight of each standardised feature.
        intercept: ``b``.
        estimator_offsets: ``b_estimator`` per estimator name.
        target_position_m, target_rotation_deg: what a correct pose means.
        description: what the model was fitted on, and when.
    """

    features: tuple[str, ...]
    mean: tuple[float, ...]
    scale: tuple[float, ...]
    weights: tuple[float, ...]
    intercept: float
    estimator_offsets: Mapping[str, float]
    target_position_m: float = 0.25
    target_rotation_deg: float = 5.0
    description: str = ""

    def __post_init__(self) -> None:
        unknown = [name for name in self.features if name not in FEATURES]
        if unknown:
            raise ValueError(f"unknown confidence features {unknown}; known: {', '.join(FEATURES)}")
        sizes = {len(self.features), len(self.mean), len(self.scale), len(self.weights)}
        if len(sizes) != 1:
            raise ValueError("features, mean, scale and weights differ in length")
        if any(not s > 0.0 for s in self.scale):
            raise ValueError("every feature scale must be positive")

    def logit(self, stats: Mapping[str, float], estimator: str) -> float:
        x = (feature_vector(stats, self.features) - np.asarray(self.mean)) / np.asarray(self.scale)
        offset = self.estimator_offsets.get(base_estimator(estimator), 0.0)
        return float(self.intercept + offset + x @ np.asarray(self.weights))

    def confidence(self, stats: Mapping[str, float], estimator: str) -> float:
        """P(pose within the target) for a localized result with ``stats`` by ``estimator``."""
        z = self.logit(stats, estimator)
        return float(1.0 / (1.0 + math.exp(-z)) if z >= 0 else math.exp(z) / (1.0 + math.exp(z)))

    def to_json(self) -> dict[str, Any]:
        return {
            "format_version": FORMAT_VERSION,
            "description": self.description,
            "target": {
                "max_position_m": self.target_position_m,
                "max_rotation_deg": self.target_rotation_deg,
            },
            "features": list(self.features),
            "mean": list(self.mean),
            "scale": list(self.scale),
            "weights": list(self.weights),
            "intercept": self.intercept,
            "estimator_offsets": dict(self.estimator_offsets),
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> ConfidenceModel:
        """Raises:
        ValueError: another format version, or inconsistent coefficients."""
        if data.get("format_version") != FORMAT_VERSION:
            raise ValueError(
                f"confidence calibration format {data.get('format_version')!r}; "
                f"this service reads {FORMAT_VERSION}"
            )
        return cls(
            features=tuple(data["features"]),
            mean=tuple(float(v) for v in data["mean"]),
            scale=tuple(float(v) for v in data["scale"]),
            weights=tuple(float(v) for v in data["weights"]),
            intercept=float(data["intercept"]),
            estimator_offsets={k: float(v) for k, v in data["estimator_offsets"].items()},
            target_position_m=float(data["target"]["max_position_m"]),
            target_rotation_deg=float(data["target"]["max_rotation_deg"]),
            description=str(data.get("description", "")),
        )

    @classmethod
    def load(cls, path: Path) -> ConfidenceModel:
        return cls.from_json(json.loads(path.read_text()))

    def save(self, path: Path) -> None:
        path.write_text(json.dumps(self.to_json(), indent=1) + "\n")


@cache
def default_confidence_model() -> ConfidenceModel:
    """The calibration shipped with the service (``calibration.json`` beside this module)."""
    return ConfidenceModel.load(SHIPPED_CALIBRATION)
