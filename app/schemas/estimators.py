"""Estimator names as an API enum, generated from the engine's registry."""

from __future__ import annotations

from enum import StrEnum
from typing import Annotated

from pydantic import BeforeValidator

from services.errors import UnknownComponentError
from services.estimators.registry import estimator_names, get_estimator

EstimatorEnum = StrEnum(  # type: ignore[misc]  # the members are the registry's names
    "EstimatorName", {name: name for name in estimator_names()}
)


def _known_estimator(value: object) -> object:
    """Refuse an unknown name with the registry's message, which lists the known ones."""
    if isinstance(value, str):
        try:
            get_estimator(value)
        except UnknownComponentError as exc:
            raise ValueError(str(exc)) from None
    return value


EstimatorName = Annotated[EstimatorEnum, BeforeValidator(_known_estimator)]
