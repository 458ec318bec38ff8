"""The localizer the settings describe (models, features, ONNX options, retrieval)."""

from __future__ import annotations

from app.settings import Settings
from services.components import build_localizer as build_engine_localizer
from services.pipeline import Localizer
from services.runtime.onnx import OnnxOptions
from services.runtime.threads import ThreadPlan, plan_threads


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


def build_localizer(settings: Settings) -> Localizer:
    return build_engine_localizer(
        settings.models_dir,
        settings.max_image_pixels,
        settings.features,
        onnx_options(settings),
        settings.global_model,
    )
