"""Exporter pieces that need no weights: einsums exported as MatMul, and which exported
models ``slloc models build`` treats as current."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from services.runtime.manifest import ModelEntry, file_sha256, write_entry
from tools.export.build import is_current
from tools.export.onnx_export import batched_matmul_plan

torch = pytest.importorskip("torch", reason="the export tools are not installed")
ort = pytest.importorskip("onnxruntime")
onnx = pytest.importorskip("onnx")


@pytest.mark.parametrize(
    ("equation", "plan"),
    [
        ("bhid, bhjd -> bhij", (False, True)),
        ("bhij,bhjd->bhid", (False, False)),
        ("bhji,bhjd->bhid", (True, False)),
        ("bmd,bnd->bmn", (False, True)),
        ("...id,...jd->...ij", None),  # ellipsis: left to Einsum
        ("bij,bij->bij", None),  # no contraction
        ("bij,bjk->bki", None),  # transposed output
        ("bii,bij->bij", None),  # diagonal
        ("ij,jk,kl->il", None),  # three operands
    ],
)
def testbatched_matmul_plan(equation: str, plan: tuple[bool, bool] | None) -> None:
    assert batched_matmul_plan(equation) == plan


class _Attention(torch.nn.Module):
    def forward(self, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        sim = torch.einsum("bhid, bhjd -> bhij", q, k)
        m0 = torch.einsum("bhij, bhjd -> bhid", sim.softmax(-1), v)
        m1 = torch.einsum("bhji, bhjd -> bhid", sim.softmax(-2), q)
        return torch.einsum("...id,...jd->...ij", m0, m1)


def test_exported_einsums_become_matmuls(tmp_path: Path) -> None:
    from tools.export import onnx_export

    path = tmp_path / "attention.onnx"
    n = torch.export.Dim("n", min=2, max=64)
    q, k, v = (torch.randn(1, 2, s, 8) for s in (5, 7, 7))
    onnx_export.export(
        _Attention().eval(), (q, k, v), path, ["q", "k", "v"], ["out"], [{2: n}, None, None]
    )
    ops = [node.op_type for node in onnx.load(str(path)).graph.node]
    assert ops.count("Einsum") == 1 and ops.count("MatMul") >= 3  # the ellipsis one stays
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    q = torch.randn(1, 2, 11, 8)
    (got,) = session.run(None, {"q": q.numpy(), "k": k.numpy(), "v": v.numpy()})
    np.testing.assert_allclose(got, _Attention()(q, k, v).numpy(), rtol=1e-4, atol=1e-5)


def test_older_exports_are_not_current(tmp_path: Path) -> None:
    model = tmp_path / "m.onnx"
    model.write_bytes(b"graph")
    entry = ModelEntry("m", "matcher", "m.onnx", file_sha256(model), "w", "0", {}, {})
    assert not is_current(tmp_path, "m", 1)  # not in the manifest
    write_entry(tmp_path, entry)
    assert is_current(tmp_path, "m", 1) and not is_current(tmp_path, "m", 2)
    write_entry(tmp_path, replace(entry, config={"export_version": 2}))
    assert is_current(tmp_path, "m", 2)
    model.write_bytes(b"other graph")
    assert not is_current(tmp_path, "m", 2)
