"""EfficientNet-Lite0 feature extractor (Tan & Le 2019, the "Lite" variant: ReLU6, no
squeeze-excitation, fixed stem and head), our own ``nn.Module`` whose parameter names follow the
published PyTorch port's state dict, so that its ImageNet weights load as they are
(:func:`monodbh.models.training.pretrained.load_efficientnet_lite0`, training only).

``(B, 3, S, S)`` ImageNet-normalised -> features at strides 4, 8, 16, 32 with
:data:`FEATURE_CHANNELS` = (24, 40, 112, 320) channels; ``S`` must be a multiple of 32.
Imported by :mod:`.segmenter`.
"""
from __future__ import annotations

import torch
from torch import nn

from monodbh.models.modeling.registry import IMAGENET_MEAN, IMAGENET_STD

__all__ = ["BLOCKS", "FEATURE_CHANNELS", "FEATURE_BLOCKS", "EfficientNetLite0"]

#: (repeats, kernel, stride, expand ratio, in channels, out channels) per stage (EfficientNet-B0's)
BLOCKS: tuple[tuple[int, int, int, int, int, int], ...] = (
    (1, 3, 1, 1, 32, 16), (2, 3, 2, 6, 16, 24), (2, 5, 2, 6, 24, 40), (3, 3, 2, 6, 40, 80),
    (3, 5, 1, 6, 80, 112), (4, 5, 2, 6, 112, 192), (1, 3, 1, 6, 192, 320))
#: the features handed on: after blocks 2, 4, 10 and 15 (strides 4, 8, 16, 32)
FEATURE_BLOCKS: tuple[int, ...] = (2, 4, 10, 15)
FEATURE_CHANNELS: tuple[int, ...] = (24, 40, 112, 320)
#: the pretrained weights' input: RGB in [0, 1] as (x - 0.498) / 0.502 (TF's (x*255 - 127) / 128)
_LITE_MEAN, _LITE_STD = 127.0 / 255.0, 128.0 / 255.0
_BN_EPS, _BN_MOMENTUM = 1e-3, 0.01


def _same_pad(k: int, stride: int) -> nn.Module:
    """TensorFlow's "SAME" padding for an even input: ``k - stride`` pixels, the extra one after."""
    p = max(k - stride, 0)
    return nn.ZeroPad2d((p // 2, p - p // 2, p // 2, p - p // 2))


class MBConv(nn.Module):
    """Inverted residual block: expand 1x1 -> depthwise kxk -> project 1x1 (+ identity)."""

    def __init__(self, c_in: int, c_out: int, k: int, stride: int, expand: int) -> None:
        super().__init__()
        mid = c_in * expand
        self.expand = expand != 1
        if self.expand:
            self._expand_conv = nn.Conv2d(c_in, mid, 1, bias=False)
            self._bn0 = nn.BatchNorm2d(mid, eps=_BN_EPS, momentum=_BN_MOMENTUM)
        self._pad = _same_pad(k, stride)
        self._depthwise_conv = nn.Conv2d(mid, mid, k, stride, groups=mid, bias=False)
        self._bn1 = nn.BatchNorm2d(mid, eps=_BN_EPS, momentum=_BN_MOMENTUM)
        self._project_conv = nn.Conv2d(mid, c_out, 1, bias=False)
        self._bn2 = nn.BatchNorm2d(c_out, eps=_BN_EPS, momentum=_BN_MOMENTUM)
        self.act = nn.ReLU6()
        self.skip = stride == 1 and c_in == c_out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.act(self._bn0(self._expand_conv(x))) if self.expand else x
        y = self.act(self._bn1(self._depthwise_conv(self._pad(y))))
        y = self._bn2(self._project_conv(y))
        return x + y if self.skip else y


class EfficientNetLite0(nn.Module):
    """The EfficientNet-Lite0 trunk without its head: ``(B, 3, S, S)`` -> 4 feature maps.

    The input is ImageNet-normalised like every network here; the first op maps it to the
    pretrained weights' own normalisation.

    Examples
    --------
    >>> net = EfficientNetLite0()
    >>> [f.shape[1] for f in net(torch.zeros(1, 3, 64, 64))]
    [24, 40, 112, 320]
    """

    def __init__(self) -> None:
        super().__init__()
        m, s = torch.tensor(IMAGENET_MEAN), torch.tensor(IMAGENET_STD)
        # x_lite = (x * s + m - LM) / LS = x * scale + shift
        self.register_buffer("in_scale", (s / _LITE_STD).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("in_shift", ((m - _LITE_MEAN) / _LITE_STD).view(1, 3, 1, 1),
                             persistent=False)
        self._stem_pad = _same_pad(3, 2)
        self._conv_stem = nn.Conv2d(3, 32, 3, 2, bias=False)
        self._bn0 = nn.BatchNorm2d(32, eps=_BN_EPS, momentum=_BN_MOMENTUM)
        self.act = nn.ReLU6()
        blocks = []
        for reps, k, stride, e, c_in, c_out in BLOCKS:
            for r in range(reps):
                blocks.append(MBConv(c_in if r == 0 else c_out, c_out, k, stride if r == 0 else 1, e))
        self._blocks = nn.ModuleList(blocks)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = x * self.in_scale + self.in_shift
        x = self.act(self._bn0(self._conv_stem(self._stem_pad(x))))
        feats = []
        for i, block in enumerate(self._blocks):
            x = block(x)
            if i in FEATURE_BLOCKS:
                feats.append(x)
        return feats
