"""Stem-edge network (nn.Module only; training and export import it, the runtime never does).

Input ``patch`` ``(B, 4, PATCH_H, PATCH_W)``: the stem at the rope, cut across it
(``monodbh.models.runtime.stem_edge.edge_patch``: ImageNet-normalised RGB + a 0/1 "inside the
photo" flag; columns across the stem, 64 per stem width, the stem in the middle half; rows along
it).

Layers: 3x3 convs + BatchNorm + ReLU that halve the rows only (every column kept), the mean over
the rows, then 1-D residual convs across the stem with dilations 1, 2, 4, 8, 16, 32 (about +-126
columns of context, the whole patch). Head: two per-column logits (1x1 conv), the left and the
right edge.

Output ``logits`` ``(B, 2, PATCH_W)``: for each edge a softmax over the columns.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from monodbh.models.modeling.common import Res1d
from monodbh.models.modeling.registry import IMAGENET_MEAN, IMAGENET_STD, ModelSpec, Preprocess, TensorSpec, register
from monodbh.models.runtime.stem_edge import PATCH_COLS_PER_W, PATCH_H, PATCH_LEN_W, PATCH_SPAN_W, PATCH_W

__all__ = ["StemEdgeNetConfig", "STEM_EDGE_CONFIGS", "StemEdgeNet", "stem_edge_spec", "build_stem_edge"]


@dataclass(frozen=True)
class StemEdgeNetConfig:
    """Widths of the 2-D stage (``ch``: one conv per entry; the first ``n_halve`` halve the rows)
    and of the 1-D stage (``seq_ch``, one residual block per dilation)."""

    ch: tuple[int, ...] = (24, 32, 48, 64)
    n_halve: int = 3
    seq_ch: int = 64
    dilations: tuple[int, ...] = (1, 2, 4, 8, 16, 32)


STEM_EDGE_CONFIGS: dict[str, StemEdgeNetConfig] = {
    "base": StemEdgeNetConfig(),
    "tiny": StemEdgeNetConfig(ch=(4, 6, 8), n_halve=2, seq_ch=8, dilations=(1, 2)),
}


class StemEdgeNet(nn.Module):
    """See the module docstring. ``forward(patch (B, 4, H, W)) -> logits (B, 2, W)``."""

    def __init__(self, cfg: StemEdgeNetConfig) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        cin = 4
        for i, c in enumerate(cfg.ch):
            stride = (2, 1) if i < cfg.n_halve else (1, 1)
            layers += [nn.Conv2d(cin, c, 3, stride=stride, padding=1, bias=False), nn.BatchNorm2d(c),
                       nn.ReLU(inplace=True)]
            cin = c
        self.stage2d = nn.Sequential(*layers)
        self.proj = nn.Sequential(nn.Conv1d(cin, cfg.seq_ch, 1, bias=False), nn.BatchNorm1d(cfg.seq_ch),
                                  nn.ReLU(inplace=True))
        self.stage1d = nn.Sequential(*[Res1d(cfg.seq_ch, d) for d in cfg.dilations])
        self.head = nn.Conv1d(cfg.seq_ch, 2, 1)

    def forward(self, patch: torch.Tensor) -> torch.Tensor:
        f = self.stage2d(patch).mean(dim=2)            # (B, C, W)
        return self.head(self.stage1d(self.proj(f)))   # (B, 2, W)


def stem_edge_spec(size: str) -> ModelSpec:
    """I/O contract of the stem-edge network at ``size`` (any size has the same patch)."""
    return ModelSpec(
        kind="stem_edge", size=size,
        inputs=(TensorSpec("patch", (1, 4, PATCH_H, PATCH_W),
                           description="ImageNet-normalised RGB of the patch across the stem at the rope (3) + "
                                       "inside-the-photo flag (1)"),),
        outputs=(TensorSpec("logits", (1, 2, PATCH_W),
                            description="softmax logits over the columns: the left edge (0), the right edge (1)"),),
        preprocess=(Preprocess(input="patch", mean=IMAGENET_MEAN, std=IMAGENET_STD,
                               resize="edge_patch", interpolation="linear"),),
        metric="score", higher_is_better=True,
        extra={"patch_doc": "monodbh.models.runtime.stem_edge.edge_patch: centred on the stem at the rope, "
                            "columns across the stem",
               "cols_per_width": PATCH_COLS_PER_W, "span_widths": PATCH_SPAN_W, "len_widths": PATCH_LEN_W})


@register("stem_edge", spec=stem_edge_spec)
def build_stem_edge(size: str) -> StemEdgeNet:
    """Fresh stem-edge network at ``size`` (``"base"`` ships, ``"tiny"`` for tests)."""
    if size not in STEM_EDGE_CONFIGS:
        raise ValueError(f"stem_edge has sizes {sorted(STEM_EDGE_CONFIGS)}, got {size!r}")
    return StemEdgeNet(STEM_EDGE_CONFIGS[size])
