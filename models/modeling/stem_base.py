"""Stem-base network (nn.Module only; training and export import it, the runtime never does).

Input ``strip`` ``(B, 4, STRIP_H, STRIP_W)``: the stem below the rope cut straight down its
image direction (``monodbh.models.runtime.stem_base.stem_strip``: ImageNet-normalised RGB + a 0/1
"inside the photo" flag; rows down the stem, 10 rows per stem width, the stem in the middle
quarter of the columns).

Layers: 3x3 convs + BatchNorm + ReLU that halve the width only (48 -> 2 columns, every row
kept), the mean over the columns, then 1-D residual convs along the stem with dilations
1, 2, 4, 8, 16 (about +-36 rows of context). Two heads: a per-row logit "the base is here"
(1x1 conv) and one "no visible base" logit from the mean and max over the rows.

Output ``logits`` ``(B, STRIP_H + 1)``: softmax over the rows and the no-base class.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from monodbh.models.modeling.common import Res1d
from monodbh.models.modeling.registry import IMAGENET_MEAN, IMAGENET_STD, ModelSpec, Preprocess, TensorSpec, register
from monodbh.models.runtime.stem_base import STRIP_H, STRIP_ROWS_PER_W, STRIP_SPAN_W, STRIP_W

__all__ = ["StemBaseNetConfig", "STEM_BASE_CONFIGS", "StemBaseNet", "stem_base_spec", "build_stem_base"]


@dataclass(frozen=True)
class StemBaseNetConfig:
    """Widths of the 2-D stage (``ch``: one conv per entry, each halves the
    width) and of the 1-D stage (``seq_ch``, one residual block per dilation)."""

    ch: tuple[int, ...] = (16, 24, 32, 48, 64)
    seq_ch: int = 64
    dilations: tuple[int, ...] = (1, 2, 4, 8, 16)


STEM_BASE_CONFIGS: dict[str, StemBaseNetConfig] = {
    "base": StemBaseNetConfig(),
    "tiny": StemBaseNetConfig(ch=(4, 6, 8, 8, 8), seq_ch=8, dilations=(1, 2)),
}


class StemBaseNet(nn.Module):
    """See the module docstring. ``forward(strip (B, 4, H, W)) -> logits (B, H + 1)``."""

    def __init__(self, cfg: StemBaseNetConfig) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        cin = 4
        for i, c in enumerate(cfg.ch):
            stride = (1, 2)
            layers += [nn.Conv2d(cin, c, 3, stride=stride, padding=1, bias=False), nn.BatchNorm2d(c),
                       nn.ReLU(inplace=True)]
            cin = c
        self.stage2d = nn.Sequential(*layers)
        self.proj = nn.Sequential(nn.Conv1d(cin, cfg.seq_ch, 1, bias=False), nn.BatchNorm1d(cfg.seq_ch),
                                  nn.ReLU(inplace=True))
        self.stage1d = nn.Sequential(*[Res1d(cfg.seq_ch, d) for d in cfg.dilations])
        self.row_head = nn.Conv1d(cfg.seq_ch, 1, 1)
        self.none_head = nn.Linear(2 * cfg.seq_ch, 1)

    def forward(self, strip: torch.Tensor) -> torch.Tensor:
        f = self.stage2d(strip).mean(dim=3)            # (B, C, H)
        f = self.stage1d(self.proj(f))                 # (B, C1, H)
        rows = self.row_head(f)[:, 0]                  # (B, H)
        g = torch.cat([f.mean(dim=2), f.amax(dim=2)], 1)
        return torch.cat([rows, self.none_head(g)], 1)  # (B, H + 1)


def stem_base_spec(size: str) -> ModelSpec:
    """I/O contract of the stem-base network at ``size`` (any size has the same strip)."""
    return ModelSpec(
        kind="stem_base", size=size,
        inputs=(TensorSpec("strip", (1, 4, STRIP_H, STRIP_W),
                           description="ImageNet-normalised RGB of the strip below the rope (3) + "
                                       "inside-the-photo flag (1)"),),
        outputs=(TensorSpec("logits", (1, STRIP_H + 1),
                            description="softmax logits: base at strip row r (0..H-1), last = no visible base"),),
        preprocess=(Preprocess(input="strip", mean=IMAGENET_MEAN, std=IMAGENET_STD,
                               resize="stem_strip", interpolation="linear"),),
        metric="score", higher_is_better=True,
        extra={"strip_doc": "monodbh.models.runtime.stem_base.stem_strip: from the stem's mid-point at the "
                            "rope, straight down the stem's image direction; row 0 = the rope",
               "rows_per_width": STRIP_ROWS_PER_W, "span_widths": STRIP_SPAN_W,
               "p_threshold": 0.7})


@register("stem_base", spec=stem_base_spec)
def build_stem_base(size: str) -> StemBaseNet:
    """Fresh stem-base network at ``size`` (``"base"`` ships, ``"tiny"`` for tests)."""
    if size not in STEM_BASE_CONFIGS:
        raise ValueError(f"stem_base has sizes {sorted(STEM_BASE_CONFIGS)}, got {size!r}")
    return StemBaseNet(STEM_BASE_CONFIGS[size])
