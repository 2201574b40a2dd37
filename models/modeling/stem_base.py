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

Size ``effl0`` (:class:`StemBaseNetL0`) reads the same strip with EfficientNet-Lite0's ImageNet
features (kept frozen in training, as the trunk network's): the strip upsampled 2x to
``(2 STRIP_H, 2 STRIP_W)``, its four feature maps reduced by 1x1 convs and stacked at stride 4
with the inside flag, two 3x3 convs that halve the width, the mean over the columns upsampled
to every strip row, then the same 1-D stage and heads. The sizes ``base`` and ``tiny`` learn
their features from the synthetic strips alone.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F

from monodbh.models.modeling.common import Res1d
from monodbh.models.modeling.efficientnet_lite import FEATURE_CHANNELS, EfficientNetLite0
from monodbh.models.modeling.registry import IMAGENET_MEAN, IMAGENET_STD, ModelSpec, Preprocess, TensorSpec, register
from monodbh.models.runtime.stem_base import STRIP_H, STRIP_ROWS_PER_W, STRIP_SPAN_W, STRIP_W

__all__ = ["StemBaseNetConfig", "STEM_BASE_CONFIGS", "StemBaseNet", "StemBaseNetL0", "stem_base_spec",
           "build_stem_base"]


@dataclass(frozen=True)
class StemBaseNetConfig:
    """Widths of the 2-D stage (``ch``: one conv per entry, each halves the
    width) and of the 1-D stage (``seq_ch``, one residual block per dilation)."""

    ch: tuple[int, ...] = (16, 24, 32, 48, 64)
    seq_ch: int = 64
    dilations: tuple[int, ...] = (1, 2, 4, 8, 16)
    #: ``"effl0"``: the 2-D stage is EfficientNet-Lite0 (:class:`StemBaseNetL0`; ``ch[0]`` is the
    #: width each feature map is reduced to, ``ch[1]`` the fusion convs')
    backbone: str = "cnn"


STEM_BASE_CONFIGS: dict[str, StemBaseNetConfig] = {
    "base": StemBaseNetConfig(),
    "tiny": StemBaseNetConfig(ch=(4, 6, 8, 8, 8), seq_ch=8, dilations=(1, 2)),
    "effl0": StemBaseNetConfig(ch=(32, 32), seq_ch=64, dilations=(1, 2, 4, 8, 16), backbone="effl0"),
}


def _add_sequence_heads(net: nn.Module, c_in: int, cfg: StemBaseNetConfig) -> None:
    """The 1-D stage and the two heads both sizes share, as ``net``'s ``proj``, ``stage1d``,
    ``row_head`` and ``none_head`` (the names the shipped files' weights carry)."""
    net.proj = nn.Sequential(nn.Conv1d(c_in, cfg.seq_ch, 1, bias=False), nn.BatchNorm1d(cfg.seq_ch),
                             nn.ReLU(inplace=True))
    net.stage1d = nn.Sequential(*[Res1d(cfg.seq_ch, d) for d in cfg.dilations])
    net.row_head = nn.Conv1d(cfg.seq_ch, 1, 1)
    net.none_head = nn.Linear(2 * cfg.seq_ch, 1)


def _sequence_logits(net: nn.Module, f: torch.Tensor) -> torch.Tensor:
    """Features along the stem ``(B, C, H)`` -> logits ``(B, H + 1)``: per-row base logits and the
    no-base logit from the mean and max over the rows (:func:`_add_sequence_heads`' layers)."""
    f = net.stage1d(net.proj(f))                       # (B, C1, H)
    rows = net.row_head(f)[:, 0]                       # (B, H)
    g = torch.cat([f.mean(dim=2), f.amax(dim=2)], 1)
    return torch.cat([rows, net.none_head(g)], 1)      # (B, H + 1)


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
        _add_sequence_heads(self, cin, cfg)

    def forward(self, strip: torch.Tensor) -> torch.Tensor:
        return _sequence_logits(self, self.stage2d(strip).mean(dim=3))


class StemBaseNetL0(nn.Module):
    """Size ``effl0`` (module docstring). ``forward(strip (B, 4, H, W)) -> logits (B, H + 1)``
    is ``decode(features(strip), strip[:, 3:])``: the trainer caches ``features`` of its
    strips, as the backbone is frozen there (and kept in eval mode while ``frozen``: its
    BatchNorm statistics are ImageNet's).

    Examples
    --------
    >>> net = StemBaseNetL0(STEM_BASE_CONFIGS["effl0"]).eval()
    >>> net(torch.zeros(2, 4, STRIP_H, STRIP_W)).shape
    torch.Size([2, 193])
    """

    def __init__(self, cfg: StemBaseNetConfig) -> None:
        super().__init__()
        lat, ch = cfg.ch[0], cfg.ch[1]
        self.frozen = True
        self.backbone = EfficientNetLite0()
        self.lat = nn.ModuleList([nn.Conv2d(c, lat, 1) for c in FEATURE_CHANNELS])
        layers: list[nn.Module] = [nn.Conv2d(lat * len(FEATURE_CHANNELS) + 1, ch, 1, bias=False),
                                   nn.BatchNorm2d(ch), nn.ReLU(inplace=True)]
        for _ in range(2):
            layers += [nn.Conv2d(ch, ch, 3, stride=(1, 2), padding=1, bias=False), nn.BatchNorm2d(ch),
                       nn.ReLU(inplace=True)]
        self.fuse = nn.Sequential(*layers)
        _add_sequence_heads(self, ch, cfg)
        self.backbone.eval()

    def train(self, mode: bool = True) -> "StemBaseNetL0":
        super().train(mode)
        if self.frozen:
            self.backbone.eval()
        return self

    def features(self, strip: torch.Tensor) -> list[torch.Tensor]:
        """Strips ``(B, 4 or 3, H, W)`` -> the backbone's four maps of the strip's RGB upsampled
        2x ``[(B, C_i, H / 2^(i+1), W / 2^(i+1))]``."""
        if strip.ndim != 4 or strip.shape[1] not in (3, 4):
            raise ValueError(f"expected strips (B, 4, H, W), got {tuple(strip.shape)}")
        H, W = strip.shape[-2:]
        return self.backbone(F.interpolate(strip[:, :3], size=(2 * H, 2 * W), mode="bilinear",
                                           align_corners=False))

    def decode(self, feats: list[torch.Tensor], inside: torch.Tensor) -> torch.Tensor:
        """:meth:`features` and the inside flag ``(B, 1, H, W)`` -> logits ``(B, H + 1)``."""
        H = inside.shape[-2]
        size = feats[0].shape[-2:]
        f = torch.cat([lat(f) if i == 0 else F.interpolate(lat(f), size=size, mode="bilinear", align_corners=False)
                       for i, (lat, f) in enumerate(zip(self.lat, feats))]
                      + [F.avg_pool2d(inside, 2)], 1)     # stride 4 of the 2x strip: half its rows
        f = self.fuse(f).mean(dim=3)                   # (B, C, H / 2)
        return _sequence_logits(self, F.interpolate(f, size=H, mode="linear", align_corners=False))

    def forward(self, strip: torch.Tensor) -> torch.Tensor:
        return self.decode(self.features(strip), strip[:, 3:])


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
def build_stem_base(size: str) -> StemBaseNet | StemBaseNetL0:
    """Fresh stem-base network at ``size`` (``"base"``, ``"effl0"`` on ImageNet features: its
    trainer loads them; ``"tiny"`` for tests)."""
    if size not in STEM_BASE_CONFIGS:
        raise ValueError(f"stem_base has sizes {sorted(STEM_BASE_CONFIGS)}, got {size!r}")
    cfg = STEM_BASE_CONFIGS[size]
    return StemBaseNetL0(cfg) if cfg.backbone == "effl0" else StemBaseNet(cfg)
