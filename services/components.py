"""Builds the localizer's heavy components once (at app start-up or in a CLI command).

Feature configurations (a local-feature extractor with its matcher) are chosen by name from
``FEATURE_CONFIGS``; ``slloc eval --features`` takes these names.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from services.errors import UnknownComponentError
from services.features.base import FeatureExtractor
from services.features.sift import SiftExtractor
from services.matching.base import Matcher
from services.matching.nearest_neighbor import NearestNeighborMatcher
from services.pipeline import Localizer
from services.retrieval.thumbnail import ThumbnailDescriptor

logger = logging.getLogger(__name__)

FeatureFactory = Callable[[Path], tuple[FeatureExtractor, Matcher]]


def _sift(models_dir: Path) -> tuple[FeatureExtractor, Matcher]:
    """OpenCV SIFT (RootSIFT) + mutual-nearest-neighbour matching; needs no weights."""
    return SiftExtractor(), NearestNeighborMatcher()


# name → factory of (extractor, matcher) from the models directory
FEATURE_CONFIGS: dict[str, FeatureFactory] = {"sift": _sift}

DEFAULT_FEATURES = "sift"


def feature_config_names() -> list[str]:
    return sorted(FEATURE_CONFIGS)


def build_localizer(models_dir: Path, max_pixels: int, features: str | None = None) -> Localizer:
    """The localizer with feature configuration ``features`` (default: the best available
    offline; today the weight-free SIFT pipeline) and thumbnail retrieval.

    Raises:
        UnknownComponentError: ``features`` is not a name in ``FEATURE_CONFIGS``.
    """
    name = features or DEFAULT_FEATURES
    try:
        factory = FEATURE_CONFIGS[name]
    except KeyError:
        raise UnknownComponentError(
            f"unknown feature configuration {name!r}; known: {', '.join(feature_config_names())}"
        ) from None
    extractor, matcher = factory(models_dir)
    logger.info(
        "features: %s (%s + %s), models from %s", name, extractor.name, matcher.name, models_dir
    )
    return Localizer(extractor, matcher, ThumbnailDescriptor(), max_pixels)
