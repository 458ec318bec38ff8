"""The localizer the settings describe (models, features, ONNX options, retrieval)."""

from __future__ import annotations

from app.settings import Settings
from services.components import build_localizer as build_engine_localizer
from services.pipeline import Localizer
from services.runtime.onnx import OnnxOptions


def onnx_options(settings: Settings) -> OnnxOptions:
    """Execution providers in order of preference (auto: CUDA when available, then CPU) and
    threads per operator."""
    providers = (
        ("CUDAExecutionProvider", "CPUExecutionProvider")
        if settings.onnx_providers.strip() == "auto"
        else tuple(p.strip() for p in settings.onnx_providers.split(",") if p.strip())
    )
    return OnnxOptions(providers=providers, intra_op_threads=settings.onnx_threads)


def build_localizer(settings: Settings) -> Localizer:
    return build_engine_localizer(
        settings.models_dir,
        settings.max_image_pixels,
        settings.features,
        onnx_options(settings),
        settings.global_model,
    )
