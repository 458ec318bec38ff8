"""The engine the settings describe (``EngineConfig``: models, features, ONNX options,
retrieval), the thread plan and the memory bound, resolved once at start-up."""

from __future__ import annotations

import logging
from dataclasses import replace

from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from app.settings import Settings
from db.repositories.images import ImageRepository
from services.components import EngineConfig
from services.features.configs import get_feature_config
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


def engine_config(
    settings: Settings,
    sessions: sessionmaker[Session] | None = None,
    plan: ThreadPlan | None = None,
) -> EngineConfig:
    """The engine the settings describe, resolved once: ``features`` (``auto`` becomes a
    configuration) against the models built and the extractors that described the
    database's references (none read without ``sessions``); ``plan``: the thread plan, by
    default the settings'."""
    stored: set[str] = set()
    if sessions is not None:
        try:
            with sessions() as session:
                stored = ImageRepository(session).feature_models()
        except SQLAlchemyError as exc:  # e.g. a database not migrated yet: no references
            logger.warning("features: the stored references could not be read (%s)", exc)
    return EngineConfig.resolve(
        settings.models_dir,
        settings.max_image_pixels,
        settings.features,
        stored=stored,
        onnx=onnx_options(settings),
        global_model=settings.global_model,
        wide_threads=wide_threads(plan or thread_plan(settings)),
        reference_image_cache_mib=settings.reference_image_cache_mib,
    )


def memory_inputs(settings: Settings, engine: EngineConfig) -> MemoryInputs:
    """What the memory bound depends on: each configuration served (the engine's, then the
    self-evaluations'): its model files, extractor, side and the keypoints its LightGlue sees;
    and the settings' limits."""

    def configuration(name: str, files: int) -> tuple[int, str, int, int]:
        config = get_feature_config(name)
        lightglue = (
            0 if config.lightglue is None else config.lightglue_keypoints or settings.max_keypoints
        )
        return files, config.extractor, max(config.max_side, settings.max_side), lightglue

    return MemoryInputs(
        configurations=(
            configuration(engine.features, engine.model_file_bytes()),
            *(
                configuration(
                    name, replace(engine, features=name, wide_threads=None).model_file_bytes()
                )
                for name in settings.parsed_evaluation_features()
                if name != engine.features
            ),
        ),
        body_memory_mib=settings.body_memory_mib,
        max_image_pixels=settings.max_image_pixels,
        max_keypoints=settings.max_keypoints,
        max_top_k=settings.max_top_k,
        reference_cache_mib=settings.reference_cache_mib,
        # only configurations that refine their matches keep reference images
        reference_image_cache_mib=settings.reference_image_cache_mib
        if any(
            get_feature_config(name).refine_matches
            for name in (engine.features, *settings.parsed_evaluation_features())
        )
        else 0,
        computing_memory_mib=settings.computing_memory_mib,
    )


def service_memory_bound(settings: Settings, engine: EngineConfig) -> MemoryBound:
    """The bound on the server's resident memory (``services.runtime.memory``), retrieval
    indexes not included."""
    return memory_bound(memory_inputs(settings, engine))
