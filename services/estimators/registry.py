"""Name → estimator. Filled by explicit imports; names are API values."""

from __future__ import annotations

from services.errors import UnknownComponentError
from services.estimators.auto import AutoEstimator
from services.estimators.base import PoseEstimator
from services.estimators.e3p1 import E3p1Estimator
from services.estimators.e5p1 import E5p1Estimator
from services.estimators.essential_3pt_depth import Essential3ptDepthEstimator
from services.estimators.essential_5pt import Essential5ptEstimator
from services.estimators.local_tri_all import LocalTriAllEstimator
from services.estimators.local_tri_pairs import LocalTriPairsEstimator
from services.estimators.motion_averaging import MotionAveragingEstimator
from services.estimators.pose_approx import PoseApproxEstimator

_ESTIMATORS: dict[str, PoseEstimator] = {
    estimator.name: estimator
    for estimator in (
        PoseApproxEstimator(),
        Essential5ptEstimator(),
        Essential3ptDepthEstimator(),
        MotionAveragingEstimator(),
        E5p1Estimator(),
        E3p1Estimator(),
        LocalTriAllEstimator(),
        LocalTriPairsEstimator(),
    )
}
# auto runs the others, chosen per query
_ESTIMATORS[AutoEstimator.name] = AutoEstimator(_ESTIMATORS)

# the estimators that need depth for the query and the references, as each declares
DEPTH_ESTIMATORS = frozenset(name for name, e in _ESTIMATORS.items() if e.needs_depth)
# the estimators that use the query's depth when it is sent: those that need it, and auto
DEPTH_USING_ESTIMATORS = DEPTH_ESTIMATORS | {AutoEstimator.name}

DEFAULT_ESTIMATOR = AutoEstimator.name


def register(estimator: PoseEstimator) -> None:
    """Add ``estimator`` under its name. The API's estimator enum, its OpenAPI document and the
    contract tests read the names once, when they are imported: register before them.

    Raises:
        ValueError: the name is taken.
    """
    if estimator.name in _ESTIMATORS:
        raise ValueError(f"estimator {estimator.name!r} is registered already")
    _ESTIMATORS[estimator.name] = estimator


def estimator_names() -> list[str]:
    return sorted(_ESTIMATORS)


def get_estimator(name: str) -> PoseEstimator:
    try:
        return _ESTIMATORS[name]
    except KeyError:
        raise UnknownComponentError(
            f"unknown estimator {name!r}; known: {', '.join(estimator_names())}"
        ) from None
