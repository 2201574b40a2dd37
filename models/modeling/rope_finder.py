"""Rope finder: a small fully convolutional network (nn.Module only; training and export import it).

It marks rope pixels in a tile of the photo without the segmenter's masks, for the photos where
the band detector and the mask-guided stem search find nothing (the segmenter missed or split
the roped stem, or the rope is too faint for the hand-made red-ness contrast).

Input ``image`` ``(B, 3, TILE, TILE)``: ImageNet-normalised RGB of a tile of the pipeline's
working image at its own resolution (a far rope is 1-2 px thick: the tile is not rescaled).

Layers: an encoder of 3x3 convs + BatchNorm + ReLU at 1/2, 1/4 and 1/8 of the tile (dilated
convs at the coarse levels widen the view to about 100 px: a rope is a band across a trunk with
bark above and below), a decoder that upsamples and fuses the skips back to 1/2.

Output ``logit`` ``(B, 1, TILE/2, TILE/2)``: per output pixel (2 x 2 photo pixels), the log-odds
that it holds rope.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F

from monodbh.models.modeling.registry import IMAGENET_MEAN, IMAGENET_STD, ModelSpec, Preprocess, TensorSpec, register

__all__ = ["RopeFinderNetConfig", "ROPE_FINDER_CONFIGS", "RopeFinderNet", "rope_finder_spec", "build_rope_finder", "TILE"]

#: the exported graph's tile side in photo pixels. The network is fully convolutional: it trains
#: on 128-pixel windows of the bank's 192-pixel tiles and runs on larger tiles (fewer overlaps)
TILE: int = 384


@dataclass(frozen=True)
class RopeFinderNetConfig:
    """Channel widths at 1/2, 1/4 and 1/8 of the tile."""

    c2: int = 16
    c4: int = 32
    c8: int = 48
    c16: int = 0      #: > 0: a fourth level at 1/16 (dilated, a view of about 260 px)


ROPE_FINDER_CONFIGS: dict[str, RopeFinderNetConfig] = {
    "base": RopeFinderNetConfig(),
    "tiny": RopeFinderNetConfig(c2=4, c4=8, c8=8),
    "wide": RopeFinderNetConfig(c16=64),
}


def _cbr(cin: int, cout: int, stride: int = 1, dilation: int = 1, k: int = 3) -> nn.Sequential:
    pad = dilation * (k // 2)
    return nn.Sequential(nn.Conv2d(cin, cout, k, stride=stride, padding=pad, dilation=dilation, bias=False),
                         nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class RopeFinderNet(nn.Module):
    """See the module docstring. ``forward(image (B, 3, T, T)) -> logit (B, 1, T/2, T/2)``."""

    def __init__(self, cfg: RopeFinderNetConfig) -> None:
        super().__init__()
        c2, c4, c8 = cfg.c2, cfg.c4, cfg.c8
        self.e2 = nn.Sequential(_cbr(3, c2, stride=2), _cbr(c2, c2))
        self.e4 = nn.Sequential(_cbr(c2, c4, stride=2), _cbr(c4, c4, dilation=2))
        self.e8 = nn.Sequential(_cbr(c4, c8, stride=2), _cbr(c8, c8, dilation=2), _cbr(c8, c8, dilation=4))
        self.e16 = self.f8 = None
        if cfg.c16:
            self.e16 = nn.Sequential(_cbr(c8, cfg.c16, stride=2), _cbr(cfg.c16, cfg.c16, dilation=2),
                                     _cbr(cfg.c16, cfg.c16, dilation=4))
            self.f8 = nn.Sequential(_cbr(cfg.c16 + c8, c8, k=1), _cbr(c8, c8))
        self.f4 = nn.Sequential(_cbr(c8 + c4, c4, k=1), _cbr(c4, c4))
        self.f2 = nn.Sequential(_cbr(c4 + c2, c2, k=1), _cbr(c2, c2))
        self.head = nn.Conv2d(c2, 1, 1)
        nn.init.constant_(self.head.bias, -4.0)   # rope pixels are rare: start near their share

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        x2 = self.e2(image)
        x4 = self.e4(x2)
        x8 = self.e8(x4)
        if self.e16 is not None:
            x8 = self.f8(torch.cat([F.interpolate(self.e16(x8), scale_factor=2.0, mode="nearest"), x8], 1))
        y4 = self.f4(torch.cat([F.interpolate(x8, scale_factor=2.0, mode="nearest"), x4], 1))
        y2 = self.f2(torch.cat([F.interpolate(y4, scale_factor=2.0, mode="nearest"), x2], 1))
        return self.head(y2)


def rope_finder_spec(size: str) -> ModelSpec:
    """I/O contract of the rope finder at ``size``."""
    return ModelSpec(
        kind="rope_finder", size=size,
        inputs=(TensorSpec("image", (1, 3, TILE, TILE),
                           description="ImageNet-normalised RGB tile of the working image, not rescaled"),),
        outputs=(TensorSpec("logit", (1, 1, TILE // 2, TILE // 2),
                            description="log-odds of rope per 2 x 2 photo pixels"),),
        preprocess=(Preprocess(input="image", mean=IMAGENET_MEAN, std=IMAGENET_STD, resize="tile",
                               interpolation="none"),),
        metric="tile_auc", higher_is_better=True,
        extra={"tile": TILE, "stride": 2,
               "tiling_doc": "monodbh.models.runtime.rope_finder.RopeFinder: overlapping tiles, "
                             "each output kept away from its tile's border"})


@register("rope_finder", spec=rope_finder_spec)
def build_rope_finder(size: str) -> RopeFinderNet:
    """Fresh rope finder at ``size`` (``"base"`` ships, ``"tiny"`` for tests)."""
    if size not in ROPE_FINDER_CONFIGS:
        raise ValueError(f"rope_finder has sizes {sorted(ROPE_FINDER_CONFIGS)}, got {size!r}")
    return RopeFinderNet(ROPE_FINDER_CONFIGS[size])
