"""Tree prediction network (Li & Kan 2024, section 2.3), mobile-sized.

Generator ``G`` (the exported one)
    U-Net: input ``crop`` ``(B, 4, P, P)`` = ImageNet-normalised RGB of a square photo window
    centred on a stem-axis point + that tree's instance mask (0/1); strided 4x4 convs with
    BatchNorm + LeakyReLU 0.2 down to a ``P/32`` latent, decoder of nearest x2 Resize + 3x3 conv +
    BatchNorm + ReLU (no ConvTranspose: int8-friendly) with U-Net skips; 3x3 conv + tanh.
    Output ``silhouette`` ``(B, 2, P, P)``: channel 0 front depth ``R_n``, channel 1 thickness
    ``G_n`` in crop-relative units (see :data:`SILHOUETTE_DOC`); unconstrained outside the mask.

Cycle-GAN parts (training only)
    ``F``: the same U-Net with input ``[silhouette * mask (2), 0, mask]`` (4 channels, same
    layout as G's input so that identity losses are defined) and 3 output channels (RGB in the
    normalised space, tanh-bounded then scaled by :data:`RGB_OUT_SCALE`);
    discriminators: 4x4 stride-2 pad-1 convs + BatchNorm + LeakyReLU 0.2, then FC -> logit.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import nn

from monodbh.models.modeling.registry import (IMAGENET_MEAN, IMAGENET_STD, ModelSpec, Preprocess,
                                              TensorSpec, register)

__all__ = ["TreeNetConfig", "TREE_CONFIGS", "UNet", "PatchDiscriminator", "SILHOUETTE_DOC",
           "RGB_OUT_SCALE", "THICKNESS", "K_INFER", "MIN_CROP_PX", "tree_spec", "build_tree",
           "build_tree_cycle"]

#: Crop side at inference = K_INFER x trunk width (px), at least MIN_CROP_PX.
K_INFER: float = 4.0
MIN_CROP_PX: int = 24
#: F's tanh output is multiplied by this (ImageNet-normalised RGB spans about [-2.1, 2.6]).
RGB_OUT_SCALE: float = 2.7

SILHOUETTE_DOC = (
    "crop = square window of side S photo px (undistorted photo) centred on a stem-axis point, "
    "S = max(min_crop_px, k * trunk_width_px), resized to P; with z_ref the z (m) of that axis "
    "point, f the photo focal length (px) and c the cosine of each pixel's ray to the optical "
    "axis: R_n = (z1 - z_ref) * f / (z_ref * S), G_n = (z2 - z1) / c * f / (z_ref * S) (thickness "
    "along the ray); so z1 = z_ref * (1 + R_n * S / f), z2 = z1 + c * z_ref * G_n * S / f")

#: how ``G_n`` is measured: "ray" (along each pixel's ray, current models) or "z" (older models)
THICKNESS = "ray"


@dataclass(frozen=True)
class TreeNetConfig:
    """U-Net widths: ``ch[i]`` channels after the i-th stride-2 down conv (len = number of downs)."""

    img: int = 128
    ch: tuple[int, ...] = (16, 32, 64, 128, 256)
    disc_ch: tuple[int, ...] = (32, 64, 128, 256)


TREE_CONFIGS: dict[str, TreeNetConfig] = {
    "base": TreeNetConfig(),
    # the first long CPU run (shipped in 0.1) used these wider U-Net channels
    "wide": TreeNetConfig(ch=(24, 48, 96, 192, 256)),
    "tiny": TreeNetConfig(img=64, ch=(4, 8, 8, 16), disc_ch=(4, 8, 8, 16)),
}


def _down(c_in: int, c_out: int, norm: bool = True) -> nn.Sequential:
    layers: list[nn.Module] = [nn.Conv2d(c_in, c_out, 4, 2, 1, bias=not norm)]
    if norm:
        layers.append(nn.BatchNorm2d(c_out))
    layers.append(nn.LeakyReLU(0.2))
    return nn.Sequential(*layers)


def _up(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Upsample(scale_factor=2, mode="nearest"),
                         nn.Conv2d(c_in, c_out, 3, 1, 1, bias=False), nn.BatchNorm2d(c_out),
                         nn.ReLU())


class UNet(nn.Module):
    """U-Net ``(B, in_ch, P, P) -> (B, out_ch, P, P)`` in ``[-out_scale, out_scale]``.

    Downs: ``len(ch)`` 4x4 stride-2 convs (no norm on the first, as pix2pix), skips at every
    level; ups: nearest x2 + 3x3 conv + BN + ReLU, concatenating the matching encoder map; head:
    3x3 conv at full resolution on ``cat(up, input)`` features, tanh.
    """

    def __init__(self, in_ch: int = 4, out_ch: int = 2, ch: tuple[int, ...] = (16, 32, 64, 128, 256),
                 out_scale: float = 1.0):
        super().__init__()
        self.out_scale = out_scale
        self.downs = nn.ModuleList()
        c = in_ch
        for i, co in enumerate(ch):
            self.downs.append(_down(c, co, norm=i > 0))
            c = co
        self.ups = nn.ModuleList()
        rev = list(ch[::-1])  # deepest first
        for i in range(len(ch)):
            skip = rev[i + 1] if i + 1 < len(rev) else 0
            co = max(rev[i + 1] if i + 1 < len(rev) else ch[0], 8)
            self.ups.append(_up(c, co))
            c = co + skip
        self.head = nn.Conv2d(c + in_ch, out_ch, 3, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        feats = []
        y = x
        for d in self.downs:
            y = d(y)
            feats.append(y)
        feats = feats[:-1][::-1]  # skips, deepest first
        for i, u in enumerate(self.ups):
            y = u(y)
            if i < len(feats):
                y = torch.cat([y, feats[i]], 1)
        y = torch.tanh(self.head(torch.cat([y, x], 1)))
        return y * self.out_scale if self.out_scale != 1.0 else y


class PatchDiscriminator(nn.Module):
    """``(B, in_ch, P, P) -> logit (B, 1)``: 4x4 s2 p1 convs (BN after all but first), LReLU, FC."""

    def __init__(self, in_ch: int, img: int, ch: tuple[int, ...] = (32, 64, 128, 256)):
        super().__init__()
        layers: list[nn.Module] = []
        c, s = in_ch, img
        for i, co in enumerate(ch):
            layers += [nn.Conv2d(c, co, 4, 2, 1)] + ([nn.BatchNorm2d(co)] if i else []) + [nn.LeakyReLU(0.2)]
            c, s = co, s // 2
        self.body = nn.Sequential(*layers)
        self.fc = nn.Linear(c * s * s, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc(self.body(x).flatten(1))


def tree_spec(size: str) -> ModelSpec:
    """I/O contract of the tree network (generator G) at ``size``."""
    p = TREE_CONFIGS[size].img
    return ModelSpec(
        kind="tree", size=size,
        inputs=(TensorSpec("crop", (1, 4, p, p),
                           description="ImageNet-normalised RGB crop (3) + this tree's mask (1, 0/1)"),),
        outputs=(TensorSpec("silhouette", (1, 2, p, p),
                            description="tanh; ch0 front depth R_n, ch1 thickness G_n (crop units)"),),
        preprocess=(Preprocess(input="crop", mean=IMAGENET_MEAN, std=IMAGENET_STD,
                               resize="square_crop", interpolation="linear"),),
        metric="g_acc", higher_is_better=True,
        extra={"silhouette": SILHOUETTE_DOC, "thickness": THICKNESS, "k_infer": K_INFER, "min_crop_px": MIN_CROP_PX,
               "crop_doc": "cv2.warpAffine of the window [cx - S/2, cx + S/2) (pixel-centre "
                           "convention, see monodbh.models.runtime.tree.crop_affine), RGB bilinear with border = "
                           "mean colour, mask nearest with border 0"})


@register("tree", spec=tree_spec)
def build_tree(size: str) -> UNet:
    """Fresh generator G (crop -> silhouette) at ``size``."""
    cfg = TREE_CONFIGS[size]
    return UNet(4, 2, cfg.ch)


def build_tree_cycle(size: str) -> dict[str, nn.Module]:
    """Training-only Cycle-GAN parts: ``{"F": UNet 4->3, "D_Y": disc on [sil*m, m], "D_X": disc on RGB}``."""
    cfg = TREE_CONFIGS[size]
    return {"F": UNet(4, 3, cfg.ch, out_scale=RGB_OUT_SCALE),
            "D_Y": PatchDiscriminator(3, cfg.img, cfg.disc_ch),
            "D_X": PatchDiscriminator(3, cfg.img, cfg.disc_ch)}


def with_overrides(size: str, **kw) -> TreeNetConfig:
    """Config of ``size`` with fields replaced (experiments)."""
    return replace(TREE_CONFIGS[size], **kw)
