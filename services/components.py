"""The engine's configuration (``EngineConfig``), resolved once, and the localizer's heavy
components built from it (at app start-up or in a CLI command).

A feature configuration (a local-feature extractor with its matcher) is a row of the table in
``services/features/configs.py``, chosen by name. ONNX sessions are created once per model file
and shared by every configuration that uses it.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Collection
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from services.errors import InvalidInputError
from services.features.base import FeatureExtractor
from services.features.configs import (
    AUTO,
    AUTO_CHOICES,
    FALLBACK_FEATURES,
    PREFERRED_MODELS,
    SIFT,
    FeatureConfig,
    described_by,
    get_feature_config,
)
from services.features.keypoint_onnx import OnnxKeypointExtractor, ResizeOptions
from services.features.sift import SiftExtractor, SiftOptions
from services.localization.localizer import Localizer
from services.matching.base import Matcher
from services.matching.lightglue_onnx import OnnxLightGlueMatcher
from services.matching.nearest_neighbor import NearestNeighborMatcher
from services.references.images import ReferenceImageCache
from services.retrieval.base import GlobalDescriptor
from services.retrieval.onnx_global import OnnxGlobalDescriptor
from services.retrieval.thumbnail import ThumbnailDescriptor
from services.runtime.manifest import ModelEntry, read_manifest, verified_path
from services.runtime.memory import MIB
from services.runtime.onnx import OnnxOptions, create_session

logger = logging.getLogger(__name__)


class ModelsMissingError(RuntimeError):
    """A feature configuration needs exported models that are not in the models directory."""


@dataclass
class ModelStore:
    """The exported models of a directory, with one shared onnxruntime session per model and
    thread count."""

    models_dir: Path
    onnx: OnnxOptions = field(default_factory=OnnxOptions)
    _sessions: dict[tuple[str, int], Any] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def entry(self, name: str) -> ModelEntry:
        entry = read_manifest(self.models_dir).get(name)
        if entry is None:
            raise ModelsMissingError(
                f"model {name} is not in {self.models_dir} "
                f"(run `slloc models build --models {name}`)"
            )
        return entry

    def session(self, name: str, threads: int | None = None) -> Any:
        """The session of model ``name`` with ``threads`` intra-op threads (None: the
        store's ``onnx.intra_op_threads``)."""
        options = self.onnx if threads is None else replace(self.onnx, intra_op_threads=threads)
        key = (name, options.intra_op_threads)
        with self._lock:
            if key not in self._sessions:
                entry = self.entry(name)
                path = verified_path(self.models_dir, entry)
                self._sessions[key] = create_session(
                    path, options, list(entry.inputs), list(entry.outputs)
                )
            return self._sessions[key]


def build_features(
    config: FeatureConfig, models: ModelStore, wide_threads: int | None = None
) -> tuple[FeatureExtractor, Matcher]:
    """The extractor and matcher of ``config``, on the sessions of ``models``.
    ``wide_threads``: the threads of an extraction that borrows every idle worker: SIFT's
    OpenCV threads, or the threads of a second session of the extractor's network (None:
    extractions run on one worker's threads).

    Raises:
        ModelsMissingError: a model ``config`` needs is not built.
    """
    nearest = NearestNeighborMatcher(config.ratio, config.min_similarity)
    if config.extractor == SIFT:
        options = SiftOptions(config.max_keypoints, config.max_side)
        return SiftExtractor(options, wide_threads), nearest
    entry = models.entry(config.extractor)
    extractor = OnnxKeypointExtractor(
        models.session(config.extractor),
        config.extractor,
        entry.keypoint_budget or config.max_keypoints,
        ResizeOptions(config.max_keypoints, config.max_side),
        int(entry.config.get("side_multiple", 1)),
        models.session(config.extractor, wide_threads) if wide_threads is not None else None,
    )
    if config.lightglue is None:
        return extractor, nearest
    matcher = OnnxLightGlueMatcher(
        models.session(config.lightglue),
        config.lightglue,
        config.lightglue_pairs,
        first_pass=nearest,
        lightglue_keypoints=config.lightglue_keypoints,
    )
    return extractor, matcher


def resolve_features(
    models_dir: Path, name: str | None = None, stored: Collection[str] = ()
) -> str:
    """``name``, or for ``None`` / ``"auto"`` the configuration auto picks (logged with the
    reason): of ``AUTO_CHOICES`` whose models are built and intact (and the fallback), the
    first whose extractor described references of ``stored`` (the extractor names of a
    database's references), so that an existing map keeps answering; else the first of them;
    else the weight-free fallback."""
    if name not in (None, AUTO):
        return name
    # a model file is hashed to be trusted: check a choice only when the order reaches it
    missing: dict[str, str | None] = {}

    def built(choice: str) -> bool:
        if choice == FALLBACK_FEATURES:
            return True
        if choice not in missing:
            missing[choice] = missing_models(models_dir, choice)
        return missing[choice] is None

    def held(choice: str) -> bool:
        return any(described_by(get_feature_config(choice), model) for model in stored)

    first = next((choice for choice in AUTO_CHOICES if built(choice)), FALLBACK_FEATURES)
    kept = next((c for c in (*AUTO_CHOICES, FALLBACK_FEATURES) if held(c) and built(c)), first)
    if kept != first:
        logger.warning(
            "features: %s, the features the database's references hold (set SLLOC_FEATURES "
            "and add the references again to change them)",
            kept,
        )
        return kept
    if first != FALLBACK_FEATURES:
        return first
    logger.warning(
        "features: using the weight-free %s pipeline (%s; `slloc models build` exports %s)",
        FALLBACK_FEATURES,
        "; ".join(f"{choice}: {reason}" for choice, reason in missing.items()),
        " + ".join(PREFERRED_MODELS),
    )
    return FALLBACK_FEATURES


def missing_models(models_dir: Path, name: str) -> str | None:
    """Why configuration ``name``'s models cannot be loaded from ``models_dir`` (not built, a
    file missing or altered), or None when they can."""
    entries = read_manifest(models_dir)
    try:
        for model in get_feature_config(name).models:
            if model not in entries:
                return f"{model} is not built in {models_dir}"
            verified_path(models_dir, entries[model])
    except (OSError, ValueError) as exc:
        return str(exc)
    return None


@dataclass(frozen=True)
class EngineConfig:
    """What the engine serves, resolved once (at the app's start-up, or in a CLI command) and
    handed to whatever builds or sizes it: the localizer (``build_localizer``), the memory
    bound (``model_file_bytes``) and what health and the served-features checks report.

    Attributes:
        models_dir: the exported models' folder.
        features: the feature configuration served, by name (never ``auto``: ``resolve``
            picks one).
        max_pixels: the largest decoded image, in pixels.
        onnx: the onnxruntime sessions' options.
        global_model: the ONNX global descriptor (its contract:
            ``services/retrieval/onnx_global.py``); None: thumbnails, with VLAD retrieval.
        wide_threads: the threads of an extraction that borrows every idle worker (None:
            none; ``build_features``).
        reference_image_cache_mib: the reference images kept decoded for the refinement of
            matches (``services.references.images``), MiB; 0 = none kept.
    """

    models_dir: Path
    features: str
    max_pixels: int
    onnx: OnnxOptions = field(default_factory=OnnxOptions)
    global_model: Path | None = None
    wide_threads: int | None = None
    reference_image_cache_mib: int = 64

    @classmethod
    def resolve(
        cls,
        models_dir: Path,
        max_pixels: int,
        features: str | None = None,
        *,
        stored: Collection[str] = (),
        onnx: OnnxOptions | None = None,
        global_model: Path | None = None,
        wide_threads: int | None = None,
        reference_image_cache_mib: int = 64,
    ) -> EngineConfig:
        """The configuration with ``features`` resolved (``None`` / ``"auto"``: the one
        ``resolve_features`` picks against the models built and ``stored``, the extractors
        that described a database's references).

        Raises:
            UnknownComponentError: ``features`` names no feature configuration.
        """
        name = resolve_features(models_dir, features, stored)
        get_feature_config(name)  # an unknown name fails here, not when the models load
        return cls(
            models_dir,
            name,
            max_pixels,
            onnx or OnnxOptions(),
            global_model,
            wide_threads,
            reference_image_cache_mib,
        )

    @property
    def feature_config(self) -> FeatureConfig:
        return get_feature_config(self.features)

    @property
    def vlad(self) -> bool:
        """Retrieval by VLAD over the local features (no global descriptor model)."""
        return self.global_model is None

    def model_file_bytes(self) -> int:
        """The sizes of the ONNX files the engine loads: the feature configuration's (the
        extractor's twice when it has a wide session as well) and the global descriptor's;
        models not built count 0 (the localizer then fails to build)."""
        config = self.feature_config
        entries = read_manifest(self.models_dir)
        loaded = list(config.models)
        if config.extractor in config.models and self.wide_threads:
            loaded.append(config.extractor)
        paths = [self.models_dir / entries[m].file for m in loaded if m in entries]
        if self.global_model is not None:
            paths.append(self.global_model)
        return sum(path.stat().st_size for path in paths if path.is_file())


def build_localizer(engine: EngineConfig) -> Localizer:
    """The localizer ``engine`` describes: its feature configuration on the models of its
    folder; retrieval by its global descriptor model or by thumbnails; matches refined on the
    images where the configuration asks for it.

    Raises:
        ModelsMissingError: the configuration needs models that are not built.
    """
    models = ModelStore(engine.models_dir, engine.onnx)
    extractor, matcher = build_features(engine.feature_config, models, engine.wide_threads)
    global_descriptor: GlobalDescriptor = ThumbnailDescriptor()
    if engine.global_model is not None:
        global_descriptor = OnnxGlobalDescriptor(
            create_session(engine.global_model, engine.onnx), engine.global_model
        )
    logger.info(
        "features: %s (%s + %s), models from %s; retrieval: %s",
        engine.features,
        extractor.name,
        matcher.name,
        engine.models_dir,
        global_descriptor.name,
    )
    return Localizer(
        extractor,
        matcher,
        global_descriptor,
        engine.max_pixels,
        reference_images=_refinement_cache(
            engine.feature_config, ReferenceImageCache(engine.reference_image_cache_mib * MIB)
        ),
    )


def _refinement_cache(
    config: FeatureConfig, cache: ReferenceImageCache
) -> ReferenceImageCache | None:
    """``cache`` for a configuration whose matches are refined on the images, else None."""
    return cache if config.refine_matches else None


class PresetUnavailableError(InvalidInputError):
    """A map's feature configuration is not one this server serves."""


class Localizers:
    """The localizers of the feature configurations this server serves maps with: its own
    (``engine.features``, built at start-up) and those of ``others`` whose models are built,
    each built on first use and kept; they share the server's global descriptor and models.
    """

    def __init__(self, engine: EngineConfig, served: Localizer, others: Collection[str] = ()):
        self.engine = engine
        self.served = served
        self.unavailable = {
            name: problem
            for name in others
            if name != engine.features and (problem := missing_models(engine.models_dir, name))
        }
        self.choices = tuple(
            dict.fromkeys(n for n in (engine.features, *others) if n not in self.unavailable)
        )
        self._built: dict[str, Localizer] = {engine.features: served}
        self.reference_images = served.reference_images or ReferenceImageCache(
            engine.reference_image_cache_mib * MIB
        )
        self._models = ModelStore(engine.models_dir, engine.onnx)
        self._lock = threading.Lock()

    @property
    def features(self) -> str:
        """The server's own configuration (``SLLOC_FEATURES``)."""
        return self.engine.features

    def get(self, preset: str | None = None) -> Localizer:
        """The localizer of ``preset`` (None: the server's).

        Raises:
            PresetUnavailableError: a configuration this server does not serve.
        """
        name = preset or self.engine.features
        with self._lock:
            localizer = self._built.get(name)
            if localizer is not None:
                return localizer
            if name not in self.choices:
                raise PresetUnavailableError(self.refusal(name))
            config = get_feature_config(name)
            # a second network session would cost the model's memory again; OpenCV's wider
            # threads cost none
            wide = self.engine.wide_threads if config.extractor == SIFT else None
            extractor, matcher = build_features(config, self._models, wide)
            localizer = Localizer(
                extractor,
                matcher,
                self.served.global_descriptor,
                self.served.max_pixels,
                reference_images=_refinement_cache(config, self.reference_images),
            )
            self._built[name] = localizer
        logger.info("features: %s loaded (%s + %s)", name, extractor.name, matcher.name)
        return localizer

    def for_map(
        self, max_keypoints: int | None, max_side: int | None, preset: str | None = None
    ) -> Localizer:
        """The localizer of ``preset`` with a map's keypoint budget and image size.

        Raises:
            PresetUnavailableError: a configuration this server does not serve.
            InvalidInputError: its extractor cannot honour the options.
        """
        return self.get(preset).for_map(max_keypoints, max_side)

    def refusal(self, name: str) -> str:
        """Why ``name`` is not served here, and what serves it."""
        problem = self.unavailable.get(name)
        if problem is not None:
            return f"feature configuration {name} cannot run on this server: {problem}"
        return (
            f"feature configuration {name} is not served here: this server serves "
            f"{', '.join(self.choices)} (SLLOC_FEATURES and SLLOC_EVALUATION_FEATURES); add "
            f"{name} to SLLOC_EVALUATION_FEATURES, with its models built, to serve it"
        )
