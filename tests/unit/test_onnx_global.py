"""The ONNX global-descriptor contract, with a small graph the test builds itself."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from services.components import EngineConfig, build_localizer
from services.retrieval.onnx_global import OnnxGlobalDescriptor
from services.runtime.onnx import create_session
from tools.synthetic.scene import SyntheticScene, unrelated_image


def _pooling_model(path: Path, height: int | str, width: int | str) -> np.ndarray:
    """(1, 3, H, W) → global average pool → a fixed 3 → 8 projection; returns the projection."""
    projection = np.random.default_rng(0).normal(size=(3, 8)).astype(np.float32)
    graph = helper.make_graph(
        [
            helper.make_node("GlobalAveragePool", ["image"], ["pooled"]),
            helper.make_node("Flatten", ["pooled"], ["flat"]),
            helper.make_node("MatMul", ["flat", "projection"], ["descriptor"]),
        ],
        "pool",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, height, width])],
        [helper.make_tensor_value_info("descriptor", TensorProto.FLOAT, [1, 8])],
        [numpy_helper.from_array(projection, "projection")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    onnx.save(model, str(path))
    return projection


@pytest.mark.parametrize("size", [(64, 48), ("height", "width")])
def test_descriptor_follows_the_contract(tmp_path: Path, size: tuple[int | str, int | str]) -> None:
    path = tmp_path / "pool.onnx"
    projection = _pooling_model(path, *size)
    descriptor = OnnxGlobalDescriptor(create_session(path), path, max_side=100)
    image = unrelated_image(1, 320, 240)
    got = descriptor.compute(image, features=None)  # type: ignore[arg-type]
    mean = (image.reshape(-1, 3).astype(np.float32) / 255.0).mean(axis=0)
    expected = ((mean - [0.485, 0.456, 0.406]) / [0.229, 0.224, 0.225]) @ projection
    np.testing.assert_allclose(got, expected / np.linalg.norm(expected), atol=2e-3)
    assert descriptor.name.startswith("onnx-pool-")


def test_model_with_the_wrong_input_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "flat.onnx"
    graph = helper.make_graph(
        [helper.make_node("Identity", ["x"], ["y"])],
        "flat",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 8])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 8])],
    )
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), str(path))
    with pytest.raises(ValueError, match=r"\(1, 3, H, W\) input"):
        OnnxGlobalDescriptor(create_session(path), path)


def test_localizer_uses_the_model(tmp_path: Path, scene: SyntheticScene) -> None:
    path = tmp_path / "pool.onnx"
    _pooling_model(path, "height", "width")
    localizer = build_localizer(
        EngineConfig.resolve(tmp_path / "no-models", 40_000_000, "sift", global_model=path)
    )
    assert localizer.global_descriptor.name.startswith("onnx-pool-")
    view = scene.views(1, stream=5, prefix="v")[0]
    vector = localizer.global_descriptor.compute(
        view.image, localizer.extractor.extract(view.image)
    )
    assert vector.shape == (8,) and abs(float(np.linalg.norm(vector)) - 1.0) < 1e-5
