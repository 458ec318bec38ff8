"""Builds the localizer's heavy components once (at app start-up or in a CLI command).

Feature configurations (a local-feature extractor with its matcher) are chosen by name from
``FEATURE_CONFIGS``; ``slloc eval --features`` takes these names. ONNX sessions are created
once per model file and shared by every configuration that uses it.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from services.errors import UnknownComponentError
from services.features.base import FeatureExtractor
from services.features.keypoint_onnx import OnnxKeypointExtractor, ResizeOptions
from services.features.sift import SiftExtractor
from services.matching.base import Matcher
from services.matching.lightglue_onnx import OnnxLightGlueMatcher
from services.matching.nearest_neighbor import NearestNeighborMatcher
from services.pipeline import Localizer
from services.retrieval.base import GlobalDescriptor
from services.retrieval.onnx_global import OnnxGlobalDescriptor
from services.retrieval.thumbnail import ThumbnailDescriptor
from services.runtime.manifest import ModelEntry, read_manifest, verified_path
from services.runtime.onnx import OnnxOptions, create_session

logger = logging.getLogger(__name__)

AUTO = "auto"


class ModelsMissingError(RuntimeError):
    """A feature configuration needs exported models that are not in the models directory."""


@dataclass
class ModelStore:
    """The exported models of a directory, with one shared onnxruntime session per model."""

    models_dir: Path
    onnx: OnnxOptions = field(default_factory=OnnxOptions)
    _sessions: dict[str, Any] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def entry(self, name: str) -> ModelEntry:
        entry = read_manifest(self.models_dir).get(name)
        if entry is None:
            raise ModelsMissingError(
                f"model {name} is not in {self.models_dir} "
                f"(run `slloc models build --models {name}`)"
            )
        return entry

    def session(self, name: str) -> Any:
        with self._lock:
            if name not in self._sessions:
                entry = self.entry(name)
                path = verified_path(self.models_dir, entry)
                self._sessions[name] = create_session(
                    path, self.onnx, list(entry.inputs), list(entry.outputs)
                )
            return self._sessions[name]


FeatureFactory = Callable[[ModelStore], tuple[FeatureExtractor, Matcher]]


def _sift(models: ModelStore) -> tuple[FeatureExtractor, Matcher]:
    """OpenCV SIFT (RootSIFT) + mutual-nearest-neighbour matching; needs no weights."""
    return SiftExtractor(), NearestNeighborMatcher()


def _learned(
    options: ResizeOptions,
    lightglue_pairs: int | None,
    model: str,
    lightglue_keypoints: int | None = None,
) -> FeatureFactory:
    """An exported keypoint extractor ``model``; LightGlue for its features (the manifest's
    ``matcher``) on the ``lightglue_pairs`` best nearest-neighbour pairs (None: every pair)
    with each image's ``lightglue_keypoints`` best keypoints (None: all), or for 0 nearest
    neighbours alone (LightGlue need not be built)."""

    def factory(models: ModelStore) -> tuple[FeatureExtractor, Matcher]:
        entry = models.entry(model)
        extractor = OnnxKeypointExtractor(
            models.session(model), model, entry.keypoint_budget or options.max_keypoints, options
        )
        matcher_name = str(entry.config.get("matcher", f"lightglue-{model.split('-')[0]}"))
        matcher: Matcher
        if lightglue_pairs == 0:
            matcher = NearestNeighborMatcher(ratio=0.95)
        else:
            matcher = OnnxLightGlueMatcher(
                models.session(matcher_name),
                matcher_name,
                lightglue_pairs,
                lightglue_keypoints=lightglue_keypoints,
            )
        return extractor, matcher

    return factory


# name → factory of (extractor, matcher). ALIKED-n16 with 1024 keypoints; mutual nearest
# neighbours on every retrieved pair, then LightGlue on the pairs with the most of them (the
# others keep theirs). "aliked" (default): 640 px, LightGlue on 3 pairs with each image's
# 512 best keypoints (~0.2 s a pair on two cores); "aliked-fast": 480 px, LightGlue on 1 pair
# with 256 keypoints; "aliked-full": 640 px, LightGlue on every pair with all 1024 (slowest,
# ~0.7 s a pair); "aliked-nn": 640 px, nearest neighbours only. "disk": DISK (DISK_KEYPOINTS
# keypoints) + LightGlue on 3 pairs, "disk-fast": DISK + nearest neighbours; both need
# `slloc models build --models disk,lightglue-disk`.
DISK_KEYPOINTS = 1024
FEATURE_CONFIGS: dict[str, FeatureFactory] = {
    "sift": _sift,
    "aliked": _learned(ResizeOptions(1024, 640), 3, "aliked-n16", lightglue_keypoints=512),
    "aliked-full": _learned(ResizeOptions(1024, 640), None, "aliked-n16"),
    "aliked-fast": _learned(ResizeOptions(1024, 480), 1, "aliked-n16", lightglue_keypoints=256),
    "aliked-nn": _learned(ResizeOptions(1024, 640), 0, "aliked-n16"),
    "disk": _learned(ResizeOptions(DISK_KEYPOINTS, 640), 3, "disk"),
    "disk-fast": _learned(ResizeOptions(DISK_KEYPOINTS, 640), 0, "disk"),
}

PREFERRED_FEATURES = "aliked"  # what "auto" picks when its models are built
PREFERRED_MODELS = ("aliked-n16", "lightglue-aliked")
FALLBACK_FEATURES = "sift"  # what "auto" picks otherwise: needs no weights


def resolve_features(models_dir: Path, name: str | None = None) -> str:
    """``name``, or for ``None`` / ``"auto"`` the configuration auto picks: the preferred
    one when its models are built and intact, else the weight-free fallback (logged)."""
    if name not in (None, AUTO):
        return name
    entries = read_manifest(models_dir)
    try:
        for model in PREFERRED_MODELS:
            if model not in entries:
                raise ModelsMissingError(f"{model} is not built in {models_dir}")
            verified_path(models_dir, entries[model])
    except (ModelsMissingError, OSError, ValueError) as exc:
        logger.warning(
            "features: using the weight-free %s pipeline (%s; `slloc models build` exports "
            "ALIKED + LightGlue)",
            FALLBACK_FEATURES,
            exc,
        )
        return FALLBACK_FEATURES
    return PREFERRED_FEATURES


def feature_config_names() -> list[str]:
    return sorted(FEATURE_CONFIGS)


def build_localizer(
    models_dir: Path,
    max_pixels: int,
    features: str | None = None,
    onnx: OnnxOptions | None = None,
    global_model: Path | None = None,
) -> Localizer:
    """The localizer with feature configuration ``features``; retrieval by the ONNX model at
    ``global_model`` (its contract: ``services/retrieval/onnx_global.py``) or by thumbnails.

    ``None`` or ``"auto"`` takes ``PREFERRED_FEATURES`` when its models are in ``models_dir``
    and the weight-free ``FALLBACK_FEATURES`` otherwise (logged with the reason).

    Raises:
        UnknownComponentError: ``features`` is not a name in ``FEATURE_CONFIGS``.
        ModelsMissingError: a named configuration needs models that are not built.
    """
    name = resolve_features(models_dir, features)
    try:
        factory = FEATURE_CONFIGS[name]
    except KeyError:
        raise UnknownComponentError(
            f"unknown feature configuration {name!r}; known: "
            f"{', '.join([AUTO, *feature_config_names()])}"
        ) from None
    onnx = onnx or OnnxOptions()
    extractor, matcher = factory(ModelStore(models_dir, onnx))
    global_descriptor: GlobalDescriptor = ThumbnailDescriptor()
    if global_model is not None:
        global_descriptor = OnnxGlobalDescriptor(create_session(global_model, onnx), global_model)
    logger.info(
        "features: %s (%s + %s), models from %s; retrieval: %s",
        name,
        extractor.name,
        matcher.name,
        models_dir,
        global_descriptor.name,
    )
    return Localizer(extractor, matcher, global_descriptor, max_pixels)
