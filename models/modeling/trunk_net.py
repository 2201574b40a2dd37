"""Trunk network: a tree's stem told from its crown, on ImageNet-pretrained features.

:class:`TrunkNet` is EfficientNet-Lite0's trunk (:class:`~.efficientnet_lite.EfficientNetLite0`,
its ImageNet weights kept frozen in training) and :class:`TrunkNetHead`, a small decoder over its
four feature maps (strides 4, 8, 16 and 32): each map to ``lat`` channels by a 1x1 conv,
upsampled to stride 4 and stacked, then 3x3 convs with growing dilations and a 1x1 conv to one
trunk logit per pixel. The segmenter's trunk head reads features learnt on synthetic scenes
only; these were learnt on real photos (``docs/decisions/trunk-head.md``).

Imported by the training code; nn.Modules only.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F

from monodbh.models.modeling.common import dilated_body
from monodbh.models.modeling.efficientnet_lite import FEATURE_CHANNELS, EfficientNetLite0

__all__ = ["TrunkNetConfig", "TrunkNetHead", "TrunkNet", "trunk_net_spec"]


@dataclass(frozen=True)
class TrunkNetConfig:
    """``lat``: channels each feature map is reduced to; ``ch``: the decoder's width;
    ``dilations``: one 3x3 conv per entry."""
    lat: int = 32
    ch: int = 48
    dilations: tuple[int, ...] = (1, 2, 4, 8)


class TrunkNetHead(nn.Module):
    """Four feature maps ``[(B, C_i, h / 2^i, w / 2^i)]`` (:data:`FEATURE_CHANNELS`) -> trunk
    logits ``(B, 1, h, w)`` at the first map's resolution.

    Examples
    --------
    >>> head = TrunkNetHead()
    >>> fs = [torch.zeros(2, c, 16 >> i, 16 >> i) for i, c in enumerate(FEATURE_CHANNELS)]
    >>> head(fs).shape
    torch.Size([2, 1, 16, 16])
    """

    def __init__(self, cfg: TrunkNetConfig = TrunkNetConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        self.lat = nn.ModuleList([nn.Conv2d(c, cfg.lat, 1) for c in FEATURE_CHANNELS])
        c_in = cfg.lat * len(FEATURE_CHANNELS)
        self.body = dilated_body(c_in, cfg.ch, cfg.dilations)
        self.out = nn.Conv2d(cfg.ch if cfg.dilations else c_in, 1, 1)

    def forward(self, feats: list[torch.Tensor]) -> torch.Tensor:
        if len(feats) != len(self.lat) or any(f.shape[1] != c for f, c in zip(feats, FEATURE_CHANNELS)):
            raise ValueError(f"expected {len(self.lat)} feature maps of {FEATURE_CHANNELS} channels, "
                             f"got {[tuple(f.shape) for f in feats]}")
        size = feats[0].shape[-2:]
        x = torch.cat([lat(f) if i == 0 else F.interpolate(lat(f), size=size, mode="bilinear", align_corners=False)
                       for i, (lat, f) in enumerate(zip(self.lat, feats))], 1)
        return self.out(self.body(x))


class TrunkNet(nn.Module):
    """ImageNet-normalised photo ``(B, 3, S, S)`` -> trunk logits ``(B, 1, S / 4, S / 4)``.

    Examples
    --------
    >>> TrunkNet()(torch.zeros(1, 3, 64, 64)).shape
    torch.Size([1, 1, 16, 16])
    """

    def __init__(self, cfg: TrunkNetConfig = TrunkNetConfig()) -> None:
        super().__init__()
        self.backbone = EfficientNetLite0()
        self.head = TrunkNetHead(cfg)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.ndim != 4 or x.shape[1] != 3:
            raise ValueError(f"expected images (B, 3, S, S), got {tuple(x.shape)}")
        return self.head(self.backbone(x))


def trunk_net_spec(side: int = 256, threshold: float = 0.5, info: dict | None = None):
    """I/O contract of the trunk network's ONNX file (kind ``"trunk_net"``): the photo or tile
    stretched to ``(1, 3, side, side)`` and ImageNet-normalised (the segmenter's preprocessing)
    in, ``trunk_logits`` ``(1, 1, side / 4, side / 4)`` out; ``extra``: ``trunk_threshold`` and
    ``info``."""
    from monodbh.models.modeling.registry import ModelSpec, Preprocess, TensorSpec
    return ModelSpec(
        kind="trunk_net", size="effl0",
        inputs=(TensorSpec("image", (1, 3, side, side), "float32",
                           "RGB photo or tile resized (stretched) to SxS, /255, ImageNet mean/std"),),
        outputs=(TensorSpec("trunk_logits", (1, 1, side // 4, side // 4), "float32",
                            "trunk logit per pixel at 1/4 input resolution (a tree's stem and the rope "
                            "on it; not branches or foliage)"),),
        preprocess=(Preprocess(input="image"),), metric="trunk_iou", higher_is_better=True,
        extra={"trunk_threshold": threshold, "info": info or {}})
