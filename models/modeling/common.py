"""Shared torch building blocks for the networks in ``monodbh.models.modeling``.

Everything here exports to ONNX opset 17 with the legacy (TorchScript) exporter and runs in
onnxruntime; blocks avoid boolean indexing and data-dependent shapes.
"""
from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

__all__ = ["ConvBNAct", "dilated_body", "BasicBlock", "Res1d", "MLP", "sine_position_encoding", "count_parameters",
           "NEG_INF"]

#: Large negative float used for additive attention masks (finite: safe for softmax, fp16 and
#: for quantisation tools that read tensor ranges).
NEG_INF: float = -1.0e4


class ConvBNAct(nn.Sequential):
    """Conv2d (no bias) -> BatchNorm2d -> activation (ReLU by default; ``act=None`` for none).

    Shapes: ``(B, c_in, H, W) -> (B, c_out, H / stride, W / stride)``.
    """

    def __init__(self, c_in: int, c_out: int, k: int = 3, stride: int = 1, groups: int = 1,
                 act: type[nn.Module] | None = nn.ReLU) -> None:
        layers: list[nn.Module] = [
            nn.Conv2d(c_in, c_out, k, stride, k // 2, groups=groups, bias=False),
            nn.BatchNorm2d(c_out),
        ]
        if act is not None:
            layers.append(act())
        super().__init__(*layers)


def dilated_body(c_in: int, ch: int, dilations: tuple[int, ...]) -> nn.Sequential:
    """One 3x3 conv (no bias) -> BatchNorm -> ReLU per dilation (padding = dilation), ``c_in``
    then ``ch`` channels. Shapes: ``(B, c_in, H, W) -> (B, ch, H, W)`` (``c_in`` out without
    dilations)."""
    layers: list[nn.Module] = []
    c = c_in
    for d in dilations:
        layers += [nn.Conv2d(c, ch, 3, padding=d, dilation=d, bias=False), nn.BatchNorm2d(ch), nn.ReLU(inplace=True)]
        c = ch
    return nn.Sequential(*layers)


class Res1d(nn.Module):
    """1-D residual block: dilated 3-tap Conv1d (no bias) -> BatchNorm1d, added to the input, ReLU.

    Shapes: ``(B, c, L) -> (B, c, L)`` (``d``: the dilation, also the padding).
    """

    def __init__(self, c: int, d: int) -> None:
        super().__init__()
        self.conv = nn.Conv1d(c, c, 3, padding=d, dilation=d, bias=False)
        self.bn = nn.BatchNorm1d(c)
        self.act = nn.ReLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(x + self.bn(self.conv(x)))


class BasicBlock(nn.Module):
    """ResNet basic block (two 3x3 ConvBN, identity or 1x1 projection shortcut), ReLU.

    Shapes: ``(B, c_in, H, W) -> (B, c_out, H / stride, W / stride)``.
    """

    def __init__(self, c_in: int, c_out: int, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = ConvBNAct(c_in, c_out, 3, stride)
        self.conv2 = ConvBNAct(c_out, c_out, 3, 1, act=None)
        self.short = (nn.Identity() if stride == 1 and c_in == c_out
                      else ConvBNAct(c_in, c_out, 1, stride, act=None))
        self.act = nn.ReLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.conv2(self.conv1(x)) + self.short(x))


class MLP(nn.Module):
    """Plain MLP: ``n_layers`` Linear layers with ReLU between. ``(..., d_in) -> (..., d_out)``."""

    def __init__(self, d_in: int, d_hidden: int, d_out: int, n_layers: int) -> None:
        super().__init__()
        dims = [d_in] + [d_hidden] * (n_layers - 1) + [d_out]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if i < len(self.layers) - 1:
                x = F.relu(x)
        return x


def sine_position_encoding(h: int, w: int, dim: int, temperature: float = 10000.0,
                           device: torch.device | None = None) -> torch.Tensor:
    """DETR-style 2-D sine positional encoding, normalised coordinates.

    Returns
    -------
    torch.Tensor
        ``(h * w, dim)`` float32 (row-major over ``(h, w)``); a constant in exported graphs.
    """
    if dim % 4:
        raise ValueError("dim must be a multiple of 4")
    npf = dim // 2
    y = (torch.arange(h, dtype=torch.float32, device=device) + 0.5) / h * 2 * math.pi
    x = (torch.arange(w, dtype=torch.float32, device=device) + 0.5) / w * 2 * math.pi
    dim_t = torch.arange(npf, dtype=torch.float32, device=device)
    dim_t = temperature ** (2 * torch.div(dim_t, 2, rounding_mode="floor") / npf)
    px = x[:, None] / dim_t  # (w, npf)
    py = y[:, None] / dim_t  # (h, npf)
    px = torch.stack((px[:, 0::2].sin(), px[:, 1::2].cos()), dim=2).flatten(1)
    py = torch.stack((py[:, 0::2].sin(), py[:, 1::2].cos()), dim=2).flatten(1)
    pos = torch.cat((py[:, None, :].expand(h, w, npf), px[None, :, :].expand(h, w, npf)), dim=2)
    return pos.reshape(h * w, dim)


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
