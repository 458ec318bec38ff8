"""The localizer the settings describe (models, features, ONNX options, retrieval)."""

from __future__ import annotations

import logging

from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from app.settings import Settings
from db.repositories.images import ImageRepository
from services.components import build_localizer as build_engine_localizer
from services.components import resolve_features
from services.features.configs import get_feature_config
from services.localization.localizer import Localizer
from services.runtime.manifest import read_manifest
from services.runtime.memory import MemoryBound, MemoryInputs, memory_bound
from services.runtime.onnx import OnnxOptions
from services.runtime.threads import ThreadPlan, plan_threads

logger = logging.getLogger(__name__)


def thread_plan(settings: Settings) -> ThreadPlan:
    """Localize workers and threads per operation from the settings (0 = sized from the
    cores)."""
    return plan_threads(
        settings.cpu_cores or None, settings.localize_workers or None, settings.onnx_threads or None
    )


def onnx_options(settings: Settings) -> OnnxOptions:
    """Execution providers in order of preference (auto: CUDA when available, then CPU),
    threads per operator from the thread plan, and the CPU memory arena as set (off by
    default: ``OnnxOptions``, ``tools/benchmarks/memory.py``)."""
    providers = (
        ("CUDAExecutionProvider", "CPUExecutionProvider")
        if settings.onnx_providers.strip() == "auto"
        else tuple(p.strip() for p in settings.onnx_providers.split(",") if p.strip())
    )
    return OnnxOptions(
        providers=providers,
        intra_op_threads=thread_plan(settings).threads_per_worker,
        memory_arena=settings.onnx_memory_arena,
    )


def wide_threads(plan: ThreadPlan) -> int | None:
    """The threads of a query extraction that borrows every idle worker: all the workers'
    (None with one worker: nothing to borrow)."""
    return plan.workers * plan.threads_per_worker if plan.workers > 1 else None


def served_settings(settings: Settings, sessions: sessionmaker[Session]) -> Settings:
    """``settings`` with ``features`` resolved (``auto`` becomes a configuration) against the
    models built and the extractors that described the database's references."""
    try:
        with sessions() as session:
            stored = ImageRepository(session).feature_models()
    except SQLAlchemyError as exc:  # e.g. a database not migrated yet: no references
        logger.warning("features: the stored references could not be read (%s)", exc)
        stored = set()
    features = resolve_features(settings.models_dir, settings.features, stored)
    return settings.model_copy(update={"features": features})


def build_localizer(settings: Settings) -> Localizer:
    return build_engine_localizer(
        settings.models_dir,
        settings.max_image_pixels,
        settings.features,
        onnx_options(settings),
        settings.global_model,
        wide_threads(thread_plan(settings)),
    )


def model_file_bytes(settings: Settings, plan: ThreadPlan | None = None) -> int:
    """The sizes of the ONNX files the settings' feature configuration (and global
    descriptor model) load, the extractor's twice when it has a wide session as well
    (``plan``: the thread plan, by default the settings'); models not built count 0 (the
    server then refuses to start or falls back to weight-free features)."""
    config = get_feature_config(resolve_features(settings.models_dir, settings.features))
    entries = read_manifest(settings.models_dir)
    loaded = list(config.models)
    if config.extractor in config.models and wide_threads(plan or thread_plan(settings)):
        loaded.append(config.extractor)
    paths = [settings.models_dir / entries[m].file for m in loaded if m in entries]
    if settings.global_model is not None:
        paths.append(settings.global_model)
    return sum(path.stat().st_size for path in paths if path.is_file())


def memory_inputs(settings: Settings, plan: ThreadPlan | None = None) -> MemoryInputs:
    """What the memory bound depends on, from the settings (``plan``: the thread plan, by
    default the settings')."""
    plan = plan or thread_plan(settings)
    return MemoryInputs(
        model_file_bytes=model_file_bytes(settings, plan),
        workers=plan.workers,
        queued=settings.max_queued,
        connections=settings.limit_concurrency,
        max_upload_bytes=settings.max_upload_bytes,
        max_image_pixels=settings.max_image_pixels,
        max_side=settings.max_side,
        max_keypoints=settings.max_keypoints,
        max_top_k=settings.max_top_k,
        reference_cache_mib=settings.reference_cache_mib,
    )


def service_memory_bound(settings: Settings, plan: ThreadPlan | None = None) -> MemoryBound:
    """The bound on the server's resident memory that the settings give
    (``services.runtime.memory``), retrieval indexes not included."""
    return memory_bound(memory_inputs(settings, plan))
