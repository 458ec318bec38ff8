"""Builds the localizer's heavy components once (at app start-up or in a CLI command)."""

from __future__ import annotations

import logging
from pathlib import Path

from services.features.sift import SiftExtractor
from services.matching.nearest_neighbor import NearestNeighborMatcher
from services.pipeline import Localizer
from services.retrieval.thumbnail import ThumbnailDescriptor

logger = logging.getLogger(__name__)


def build_localizer(models_dir: Path, max_pixels: int) -> Localizer:
    """The localizer with the best components available offline.

    Today: OpenCV SIFT (RootSIFT) + mutual-nearest-neighbour matching + thumbnail retrieval,
    which need no weights. ``models_dir`` is where exported ONNX models will be looked up.
    """
    logger.info(
        "features: weight-free SIFT pipeline (no exported models are used from %s)", models_dir
    )
    return Localizer(SiftExtractor(), NearestNeighborMatcher(), ThumbnailDescriptor(), max_pixels)
