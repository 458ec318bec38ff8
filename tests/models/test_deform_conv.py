"""The plain-torch ``deform_conv2d`` that stands in for torchvision's when exporting ALIKED."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="the export tools are not installed")
from tools.export.torchvision_shim import deform_conv2d  # noqa: E402


def _slow_reference(x, offset, weight, bias, padding, mask):  # type: ignore[no-untyped-def]
    """Deformable convolution by its definition, one output pixel and tap at a time."""
    x, offset, weight = x.double().numpy(), offset.double().numpy(), weight.double().numpy()
    b, c, h, w = x.shape
    o, _, kh, kw = weight.shape
    h_out, w_out = h + 2 * padding - kh + 1, w + 2 * padding - kw + 1
    out = np.zeros((b, o, h_out, w_out))

    def pixel(n: int, y: float, xx: float) -> np.ndarray:
        y0, x0 = int(np.floor(y)), int(np.floor(xx))
        value = np.zeros(c)
        for yy, xc in itertools.product((y0, y0 + 1), (x0, x0 + 1)):
            if 0 <= yy < h and 0 <= xc < w:
                value += (1 - abs(y - yy)) * (1 - abs(xx - xc)) * x[n, :, yy, xc]
        return value

    for n, i, j in itertools.product(range(b), range(h_out), range(w_out)):
        for k, (ki, kj) in enumerate(itertools.product(range(kh), range(kw))):
            dy, dx = offset[n, 2 * k, i, j], offset[n, 2 * k + 1, i, j]
            sample = pixel(n, i - padding + ki + dy, j - padding + kj + dx)
            if mask is not None:
                sample = sample * mask[n, k, i, j].item()
            out[n, :, i, j] += weight[:, :, ki, kj] @ sample
    if bias is not None:
        out += bias.double().numpy()[None, :, None, None]
    return out


@pytest.fixture
def inputs() -> tuple:  # type: ignore[type-arg]
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(2, 3, 7, 9, generator=gen)
    weight = torch.randn(4, 3, 3, 3, generator=gen)
    bias = torch.randn(4, generator=gen)
    return x, weight, bias


def test_zero_offsets_are_a_plain_convolution(inputs: tuple) -> None:  # type: ignore[type-arg]
    x, weight, bias = inputs
    offset = torch.zeros(2, 18, 7, 9)
    got = deform_conv2d(x, offset, weight, bias, padding=1)
    expected = torch.nn.functional.conv2d(x, weight, bias, padding=1)
    torch.testing.assert_close(got, expected, atol=1e-5, rtol=1e-5)


def test_integer_offsets_shift_the_input(inputs: tuple) -> None:  # type: ignore[type-arg]
    x, weight, bias = inputs
    offset = torch.zeros(2, 18, 7, 9)
    offset[:, 1::2] = 1.0  # every tap reads one pixel to the right
    got = deform_conv2d(x, offset, weight, bias, padding=1)
    # tap (ki, kj) of output (i, j) reads x[i - 1 + ki, j + kj]: zero-pad one row above and
    # below and two columns on the right, then convolve without padding
    shifted = torch.nn.functional.pad(x, (0, 2, 1, 1))
    expected = torch.nn.functional.conv2d(shifted, weight, bias)
    torch.testing.assert_close(got, expected, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("with_mask", [False, True])
def test_fractional_offsets_match_the_definition(inputs: tuple, with_mask: bool) -> None:  # type: ignore[type-arg]
    x, weight, bias = inputs
    gen = torch.Generator().manual_seed(1)
    offset = 2.5 * torch.randn(2, 18, 7, 9, generator=gen)  # some samples leave the image
    mask = torch.rand(2, 9, 7, 9, generator=gen) if with_mask else None
    got = deform_conv2d(x, offset, weight, bias, padding=1, mask=mask)
    expected = _slow_reference(x, offset, weight, bias, 1, mask)
    np.testing.assert_allclose(got.numpy(), expected, atol=1e-4)
