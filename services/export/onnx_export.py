"""torch → ONNX with the dynamo exporter, shared by the model exporters."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import onnx
import torch
from onnxscript import opset18 as op

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
