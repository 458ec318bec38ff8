"""The one place onnxruntime sessions are created (providers, threads, denormals, I/O checks)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import onnxruntime as ort

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class OnnxOptions:
    """providers: execution providers in order of preference; ones this onnxruntime build
    lacks are skipped with a warning (CPU is always appended).
    intra_op_threads: threads inside one operator; 0 lets onnxruntime use every core
        (``services/runtime/threads.py`` sizes it for the service).
    memory_arena: keep freed CPU buffers in onnxruntime's arena for reuse. Off, each run
        allocates from and returns to the system allocator: with the variable input sizes
        of keypoint and LightGlue graphs the arena grows to the largest shapes seen and never
        shrinks.
    memory_pattern: plan each run's buffers from the previous run's shapes (pays off for
        fixed input shapes only).
    """

    providers: tuple[str, ...] = ("CPUExecutionProvider",)
    intra_op_threads: int = 0
    memory_arena: bool = True
    memory_pattern: bool = True


def create_session(
    model: Path | bytes,
    options: OnnxOptions | None = None,
    expected_inputs: Sequence[str] = (),
    expected_outputs: Sequence[str] = (),
) -> Any:
    """An ``ort.InferenceSession`` for ``model`` (a file, or a serialized graph built in
    process), checked to have the named inputs/outputs.

    Denormals are flushed to zero (``session.set_denormal_as_zero``): it halves LightGlue's
    time on CPU and changes no result at float32 precision.
    """
    options = options or OnnxOptions()
    if isinstance(model, Path) and not model.is_file():
        raise FileNotFoundError(f"ONNX model {model} does not exist")
    available = set(ort.get_available_providers())
    providers = [p for p in options.providers if p in available]
    for missing in sorted(set(options.providers) - available):
        logger.info("onnxruntime has no %s here; skipping it", missing)
    if "CPUExecutionProvider" not in providers:
        providers.append("CPUExecutionProvider")
    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.intra_op_num_threads = options.intra_op_threads
    # idle pool threads would spin on cores that other requests' work needs
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.enable_cpu_mem_arena = options.memory_arena
    so.enable_mem_pattern = options.memory_pattern
    so.add_session_config_entry("session.set_denormal_as_zero", "1")
    source = str(model) if isinstance(model, Path) else model
    session = ort.InferenceSession(source, sess_options=so, providers=providers)
    inputs = {i.name for i in session.get_inputs()}
    outputs = {o.name for o in session.get_outputs()}
    missing_io = [n for n in expected_inputs if n not in inputs] + [
        n for n in expected_outputs if n not in outputs
    ]
    if missing_io:
        name = model.name if isinstance(model, Path) else "the graph"
        raise ValueError(
            f"{name} lacks {missing_io}; it has inputs {sorted(inputs)} and "
            f"outputs {sorted(outputs)}"
        )
    return session
