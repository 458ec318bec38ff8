"""Name → estimator. Filled by explicit imports; names are API values."""

from __future__ import annotations

from services.errors import UnknownComponentError
from services.estimators.base import PoseEstimator
from services.estimators.e5p1 import E5p1Estimator

_ESTIMATORS: dict[str, PoseEstimator] = {
    estimator.name: estimator for estimator in (E5p1Estimator(),)
}

DEFAULT_ESTIMATOR = "e5p1"


def estimator_names() -> list[str]:
    return sorted(_ESTIMATORS)


def get_estimator(name: str) -> PoseEstimator:
    try:
        return _ESTIMATORS[name]
    except KeyError:
        raise UnknownComponentError(
            f"unknown estimator {name!r}; known: {', '.join(estimator_names())}"
        ) from None
