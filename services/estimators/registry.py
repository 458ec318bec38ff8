"""Name → estimator. Filled by explicit imports; names are API values."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from collections.abc import Set as AbstractSet

from services.errors import UnknownComponentError
from services.estimators.auto import AutoEstimator, check_roles
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
# auto runs the others, chosen per query: its plans' roles must name registered estimators
check_roles(_ESTIMATORS)
_ESTIMATORS[AutoEstimator.name] = AutoEstimator(_ESTIMATORS)


class _Declaring(AbstractSet[str]):
    """The names of the registered estimators that ``declares`` holds for, read at each use:
    an estimator added with ``register()`` appears."""

    def __init__(self, declares: Callable[[PoseEstimator], bool]) -> None:
        self._declares = declares

    def __contains__(self, name: object) -> bool:
        estimator = _ESTIMATORS.get(name) if isinstance(name, str) else None
        return estimator is not None and self._declares(estimator)

    def __iter__(self) -> Iterator[str]:
        return iter(sorted(name for name, e in _ESTIMATORS.items() if self._declares(e)))

    def __len__(self) -> int:
        return sum(1 for _ in self)

    def __repr__(self) -> str:
        return f"{{{', '.join(self)}}}"


# the estimators that need depth for the query and the references, as each declares
DEPTH_ESTIMATORS: AbstractSet[str] = _Declaring(lambda e: e.needs_depth)
# the estimators that use the query's depth when it is sent: those that need it, and auto
DEPTH_USING_ESTIMATORS: AbstractSet[str] = _Declaring(
    lambda e: e.needs_depth or e.name == AutoEstimator.name
)

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
