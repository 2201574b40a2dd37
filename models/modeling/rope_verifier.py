"""Rope-band verifier (nn.Module only; training and export import it, the runtime never does).

Inputs ``patch`` ``(B, 5, PATCH_H, PATCH_W)``: a candidate band of the stem search cut along
its direction (``monodbh.models.runtime.rope_verifier.band_patch``: ImageNet-normalised RGB, the stem's
instance mask, inside-the-photo flag; the band on the middle row, the stem across the middle
half of the columns), and ``side`` ``(B, N_SIDE)``: the stem search's features of the band
(``runtime.rope_verifier.SIDE_FEATURES``), standardised inside the network (buffers set from the
training bank).

Layers: 3x3 convs + BatchNorm + ReLU (three of stride 2), the mean and max over the feature
map, concatenated with a small MLP of the side features; a 2-layer head.

Output ``logit`` ``(B, 1)``: log-odds that the band is the rope.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from monodbh.models.modeling.registry import IMAGENET_MEAN, IMAGENET_STD, ModelSpec, Preprocess, TensorSpec, register
from monodbh.models.runtime.rope_verifier import N_SIDE, PATCH_H, PATCH_SPAN_W, PATCH_W, SIDE_FEATURES

__all__ = ["RopeVerifierNetConfig", "ROPE_VERIFIER_CONFIGS", "RopeVerifierNet", "rope_verifier_spec", "build_rope_verifier"]


@dataclass(frozen=True)
class RopeVerifierNetConfig:
    """Conv widths (``ch``; entries with stride 2 in ``strides``) and the side MLP width."""

    ch: tuple[int, ...] = (16, 32, 32, 64, 64, 96)
    strides: tuple[int, ...] = (1, 2, 1, 2, 1, 2)
    side_ch: int = 32
    head_ch: int = 64


ROPE_VERIFIER_CONFIGS: dict[str, RopeVerifierNetConfig] = {
    "base": RopeVerifierNetConfig(),
    "tiny": RopeVerifierNetConfig(ch=(4, 8), strides=(1, 2), side_ch=4, head_ch=8),
}


class RopeVerifierNet(nn.Module):
    """See the module docstring. ``forward(patch (B, 5, H, W), side (B, N_SIDE)) -> logit (B, 1)``."""

    def __init__(self, cfg: RopeVerifierNetConfig) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        cin = 5
        for c, s in zip(cfg.ch, cfg.strides):
            layers += [nn.Conv2d(cin, c, 3, stride=s, padding=1, bias=False), nn.BatchNorm2d(c), nn.ReLU(inplace=True)]
            cin = c
        self.conv = nn.Sequential(*layers)
        self.register_buffer("side_mean", torch.zeros(N_SIDE))
        self.register_buffer("side_std", torch.ones(N_SIDE))
        self.side = nn.Sequential(nn.Linear(N_SIDE, cfg.side_ch), nn.ReLU(inplace=True))
        self.head = nn.Sequential(nn.Linear(2 * cin + cfg.side_ch, cfg.head_ch), nn.ReLU(inplace=True),
                                  nn.Linear(cfg.head_ch, 1))

    def forward(self, patch: torch.Tensor, side: torch.Tensor) -> torch.Tensor:
        f = self.conv(patch)
        g = torch.cat([f.mean(dim=(2, 3)), f.amax(dim=(2, 3)),
                       self.side((side - self.side_mean) / self.side_std)], 1)
        return self.head(g)


def rope_verifier_spec(size: str) -> ModelSpec:
    """I/O contract of the rope verifier at ``size``."""
    return ModelSpec(
        kind="rope_verifier", size=size,
        inputs=(TensorSpec("patch", (1, 5, PATCH_H, PATCH_W),
                           description="ImageNet-normalised RGB of the band patch (3) + the stem's mask (1) + "
                                       "inside-the-photo flag (1)"),
                TensorSpec("side", (1, N_SIDE), description="stem-search features: " + ", ".join(SIDE_FEATURES))),
        outputs=(TensorSpec("logit", (1, 1), description="log-odds that the band is the rope"),),
        preprocess=(Preprocess(input="patch", mean=IMAGENET_MEAN, std=IMAGENET_STD,
                               resize="band_patch", interpolation="linear"),),
        metric="auc", higher_is_better=True,
        extra={"patch_doc": "monodbh.models.runtime.rope_verifier.band_patch: centred on the band, along it; "
                            "rows are photo pixels, columns span PATCH_SPAN_W stem widths",
               "span_widths": PATCH_SPAN_W, "side_features": list(SIDE_FEATURES)})


@register("rope_verifier", spec=rope_verifier_spec)
def build_rope_verifier(size: str) -> RopeVerifierNet:
    """Fresh rope verifier at ``size`` (``"base"`` ships, ``"tiny"`` for tests)."""
    if size not in ROPE_VERIFIER_CONFIGS:
        raise ValueError(f"rope_verifier has sizes {sorted(ROPE_VERIFIER_CONFIGS)}, got {size!r}")
    return RopeVerifierNet(ROPE_VERIFIER_CONFIGS[size])
