"""CDEN: conditional depth estimation network (Li & Kan 2024, section 2.2), mobile-sized.

Generator
    input ``image`` ``(B, 3, S, S)`` (ImageNet-normalised RGB, letterboxed photo) and ``mask``
    ``(B, 1, S, S)`` (union of tree masks, 0/1) -> concatenated 4 channels ->
    :class:`~monodbh.models.modeling.swin.SwinEncoder` (patch 4, shifted windows, patch merging)
    producing maps at strides 4, 8, 16, 32, 64 -> ``ResBlock`` skips at strides 4, 16 and 64
    (the paper's ratios) -> decoder of ``UpBlock`` units (x2 bilinear Resize, 1x1 conv,
    InstanceNorm, LeakyReLU 0.2; two units between skip levels as in the paper) -> conv -> tanh.
    Output ``depth_code`` ``(B, 1, S, S)`` in ``[-1, 1]``.

Depth code (canonical-camera log depth)
    The net predicts depth for a canonical camera with focal ``f_c = F_CANON_FRAC * S`` pixels at
    the network input. ``t -> d_c = exp(ln D_MIN + (t + 1) / 2 * (ln D_MAX - ln D_MIN))`` metres,
    metric depth ``d = d_c * fx_net / f_c`` with ``fx_net`` the photo's focal length at network
    resolution (``fx_photo * S / max(W_photo, H_photo)`` with the letterbox fit; equals
    ``fx_photo * S / W_photo`` for landscape photos). Sky (GT depth 0) and letterbox padding are
    excluded from every loss.

Discriminator
    pix2pix-style conditional: ``cat(image, mask, depth_code)`` -> four 5x5 stride-4 convs
    (BatchNorm after all but the first, LeakyReLU 0.2) -> FC -> logit (the sigmoid of the paper
    is folded into ``BCEWithLogits`` in training).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import torch
from torch import nn

from monodbh.models.modeling.registry import (IMAGENET_MEAN, IMAGENET_STD, ModelSpec, Preprocess,
                                              TensorSpec, register)
from monodbh.models.modeling.swin import SwinEncoder

__all__ = ["D_MIN", "D_MAX", "F_CANON_FRAC", "CDENConfig", "CDEN_CONFIGS", "ResBlock", "UpBlock",
           "CDENGenerator", "CDENDiscriminator", "code_to_canonical_depth",
           "canonical_depth_to_code", "code_to_metric", "metric_to_code", "cden_spec",
           "build_cden", "build_cden_discriminator"]

#: Depth code range (canonical metres) and canonical focal length as a fraction of the input width.
D_MIN: float = 0.5
D_MAX: float = 100.0
F_CANON_FRAC: float = 0.8
_LN_MIN, _LN_RANGE = math.log(D_MIN), math.log(D_MAX) - math.log(D_MIN)


def code_to_canonical_depth(t: torch.Tensor) -> torch.Tensor:
    """``t`` in [-1, 1] -> canonical depth ``d_c`` metres (same shape)."""
    return torch.exp(_LN_MIN + (t + 1.0) * 0.5 * _LN_RANGE)


def canonical_depth_to_code(d_c: torch.Tensor) -> torch.Tensor:
    """Canonical depth (metres, > 0) -> code in [-1, 1] (clipped)."""
    t = 2.0 * (torch.log(d_c.clamp_min(1e-6)) - _LN_MIN) / _LN_RANGE - 1.0
    return t.clamp(-1.0, 1.0)


def _fscale(fx_net: torch.Tensor | float, size: int) -> torch.Tensor | float:
    f_c = F_CANON_FRAC * size
    if isinstance(fx_net, torch.Tensor):
        return (fx_net / f_c).reshape(-1, *([1] * 3)) if fx_net.ndim == 1 else fx_net / f_c
    return fx_net / f_c


def code_to_metric(t: torch.Tensor, fx_net: torch.Tensor | float, size: int) -> torch.Tensor:
    """Code ``(B, 1, H, W)`` -> metric depth; ``fx_net`` float or ``(B,)`` (px at net resolution)."""
    return code_to_canonical_depth(t) * _fscale(fx_net, size)


def metric_to_code(d: torch.Tensor, fx_net: torch.Tensor | float, size: int) -> torch.Tensor:
    """Metric depth ``(B, 1, H, W)`` (> 0) -> code; inverse of :func:`code_to_metric`."""
    return canonical_depth_to_code(d / _fscale(fx_net, size))


@dataclass(frozen=True)
class CDENConfig:
    """Hyper-parameters of the CDEN generator.

    ``dec`` maps decoder stride -> channels of the UpBlock unit producing that stride;
    ``skips`` maps encoder stride -> ResBlock output channels (the bottleneck stride is the
    largest key); ``fine`` > 0 adds a stride-2 3x3 conv stem on the input concatenated at stride 2
    (0 disables); ``head_k`` is the kernel of the final conv (1 or 3).
    """

    img: int = 256
    embed: int = 32
    depths: tuple[int, ...] = (2, 2, 4, 2)
    heads: tuple[int, ...] = (1, 2, 4, 8)
    ws: int = 8
    mlp_ratio: float = 4.0
    skips: dict = field(default_factory=lambda: {64: 256, 16: 64, 4: 16})
    dec: dict = field(default_factory=lambda: {32: 128, 16: 64, 8: 64, 4: 32, 2: 16, 1: 16})
    fine: int = 16
    head_k: int = 3


CDEN_CONFIGS: dict[str, CDENConfig] = {
    "base": CDENConfig(),
    # the first long CPU run (shipped in 0.1) used this wider encoder: embed 48, depths 2-2-2-2
    "wide": CDENConfig(embed=48, depths=(2, 2, 2, 2), heads=(2, 4, 8, 16)),
    "tiny": CDENConfig(img=64, embed=8, depths=(1, 1), heads=(1, 2), ws=4, mlp_ratio=2.0,
                       skips={32: 16, 16: 8, 4: 8}, dec={16: 8, 8: 8, 4: 8, 2: 8, 1: 8},
                       fine=4, head_k=3),
}


class ResBlock(nn.Module):
    """Skip-connection residual block: 1x1 projection, then ``x + IN(conv3(LReLU(IN(conv3 x))))``.

    ``(B, c_in, H, W) -> (B, c_out, H, W)``.
    """

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.proj = nn.Conv2d(c_in, c_out, 1)
        self.body = nn.Sequential(
            nn.Conv2d(c_out, c_out, 3, padding=1), nn.InstanceNorm2d(c_out, affine=True),
            nn.LeakyReLU(0.2),
            nn.Conv2d(c_out, c_out, 3, padding=1), nn.InstanceNorm2d(c_out, affine=True))
        self.act = nn.LeakyReLU(0.2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.proj(x)
        return self.act(x + self.body(x))


class UpBlock(nn.Sequential):
    """Paper UpBlock unit: bilinear x2 Resize -> conv ``k`` (1x1 default) -> InstanceNorm -> LReLU 0.2.

    ``(B, c_in, H, W) -> (B, c_out, 2H, 2W)``.
    """

    def __init__(self, c_in: int, c_out: int, k: int = 1):
        super().__init__(
            nn.Upsample(scale_factor=2, mode="bilinear", align_corners=False),
            nn.Conv2d(c_in, c_out, k, padding=k // 2),
            nn.InstanceNorm2d(c_out, affine=True),
            nn.LeakyReLU(0.2))


class CDENGenerator(nn.Module):
    """CDEN generator; ``forward(image (B,3,S,S), mask (B,1,S,S)) -> depth_code (B,1,S,S)``."""

    def __init__(self, cfg: CDENConfig = CDENConfig()):
        super().__init__()
        self.cfg = cfg
        bott = max(cfg.skips)
        n_stages = len(cfg.depths)
        last = 4 * 2 ** (n_stages - 1)
        extra = int(round(math.log2(bott / last)))
        if extra < 0 or 4 * 2 ** (n_stages - 1 + extra) != bott:
            raise ValueError(f"bottleneck stride {bott} not reachable from depths {cfg.depths}")
        self.encoder = SwinEncoder(4, (cfg.img, cfg.img), cfg.embed, cfg.depths, cfg.heads,
                                   cfg.ws, 4, cfg.mlp_ratio, extra_merges=extra)
        enc_ch = dict(zip(self.encoder.strides, self.encoder.channels))
        self.skip_strides = sorted(cfg.skips, reverse=True)
        self.skips = nn.ModuleDict({str(s): ResBlock(enc_ch[s], cfg.skips[s]) for s in self.skip_strides})
        self.fine = (nn.Sequential(nn.Conv2d(4, cfg.fine, 3, 2, 1), nn.InstanceNorm2d(cfg.fine, affine=True),
                                   nn.LeakyReLU(0.2)) if cfg.fine else None)
        ups = []
        c = cfg.skips[bott]
        stride = bott
        self.up_strides = []
        while stride > 1:
            stride //= 2
            ups.append(UpBlock(c, cfg.dec[stride]))
            c = cfg.dec[stride]
            if stride in cfg.skips:
                c += cfg.skips[stride]
            if stride == 2 and self.fine is not None:
                c += cfg.fine
            self.up_strides.append(stride)
        self.ups = nn.ModuleList(ups)
        self.head = nn.Conv2d(c, 1, cfg.head_k, padding=cfg.head_k // 2)

    def forward(self, image: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        x = torch.cat([image, mask], dim=1)
        feats = dict(zip(self.encoder.strides, self.encoder(x)))
        skip = {s: self.skips[str(s)](feats[s]) for s in self.skip_strides}
        y = skip[self.skip_strides[0]]
        for stride, up in zip(self.up_strides, self.ups):
            y = up(y)
            parts = [y]
            if stride in skip:
                parts.append(skip[stride])
            if stride == 2 and self.fine is not None:
                parts.append(self.fine(x))
            if len(parts) > 1:
                y = torch.cat(parts, dim=1)
        return torch.tanh(self.head(y))


class CDENDiscriminator(nn.Module):
    """Conditional discriminator ``(image, mask, code) -> logit (B, 1)``.

    Four 5x5 stride-4 pad-2 convs (``ch``), BatchNorm after all but the first, LeakyReLU 0.2,
    then a linear layer on the flattened map.
    """

    def __init__(self, img: int = 256, ch: tuple[int, ...] = (32, 64, 128, 256), in_ch: int = 5):
        super().__init__()
        layers: list[nn.Module] = []
        c, s = in_ch, img
        for i, co in enumerate(ch):
            layers.append(nn.Conv2d(c, co, 5, 4, 2))
            if i > 0:
                layers.append(nn.BatchNorm2d(co))
            layers.append(nn.LeakyReLU(0.2))
            c, s = co, (s + 4 - 5) // 4 + 1
        self.body = nn.Sequential(*layers)
        self.fc = nn.Linear(c * s * s, 1)

    def forward(self, image: torch.Tensor, mask: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
        return self.fc(self.body(torch.cat([image, mask, code], 1)).flatten(1))


def _depth_extra(cfg: CDENConfig) -> dict:
    return {
        "depth_code": {
            "kind": "canonical_log_depth", "d_min_m": D_MIN, "d_max_m": D_MAX,
            "f_canon_px": F_CANON_FRAC * cfg.img, "f_canon_frac": F_CANON_FRAC,
            "formula": "d_c = exp(ln d_min + (t+1)/2*(ln d_max - ln d_min)); "
                       "depth_m = d_c * fx_net / f_canon_px; fx_net = fx_photo * S / max(W, H)",
        },
        "fit": "letterbox",
        "fit_doc": "photo resized (aspect kept, INTER_AREA) so max(W,H) = S, centred, padded with "
                   "the mean colour (0 after normalisation) and mask 0",
        "mask_input": "union of tree instance masks, resized like the photo (nearest), 0/1 float",
        "sky_masked": True,
    }


def cden_spec(size: str) -> ModelSpec:
    """I/O contract of CDEN at ``size``."""
    cfg = CDEN_CONFIGS[size]
    s = cfg.img
    return ModelSpec(
        kind="depth", size=size,
        inputs=(TensorSpec("image", (1, 3, s, s), description="ImageNet-normalised RGB, letterboxed"),
                TensorSpec("mask", (1, 1, s, s), description="union of tree masks, 0/1, letterboxed")),
        outputs=(TensorSpec("depth_code", (1, 1, s, s),
                            description="canonical log-depth code in [-1, 1] (see extra.depth_code)"),),
        preprocess=(Preprocess(input="image", mean=IMAGENET_MEAN, std=IMAGENET_STD,
                               resize="letterbox", interpolation="area"),),
        metric="delta1", higher_is_better=True, extra=_depth_extra(cfg))


@register("depth", spec=cden_spec)
def build_cden(size: str) -> CDENGenerator:
    """Fresh CDEN generator at ``size`` (``"tiny"``, ``"base"``)."""
    return CDENGenerator(CDEN_CONFIGS[size])


def build_cden_discriminator(size: str) -> CDENDiscriminator:
    """Discriminator matching the generator size."""
    cfg = CDEN_CONFIGS[size]
    return CDENDiscriminator(cfg.img, (8, 8, 16, 16) if size == "tiny" else (32, 64, 128, 256))


def with_overrides(size: str, **kw) -> CDENConfig:
    """Config of ``size`` with fields replaced (experiments)."""
    return replace(CDEN_CONFIGS[size], **kw)
