"""The segmenter's trunk head (nn.Module only; training and export import it, the runtime never does).

The segmenter labels a whole tree "tree": crown, limbs and trunk together, as the paper's
Mask2Former does. A forester's trunk is the stem alone. This head reads the segmenter's own
``mask_features`` (``(B, D, S/4, S/4)``, the per-pixel embedding its mask queries are dotted with)
and gives one logit per pixel: the pixel is a trunk (a tree's stem, the rope on it included; not
its branches or foliage). It is trained with the segmenter frozen, so the segmenter's other outputs
stay exactly as they were; :mod:`monodbh.models.training.trunk_head` ships it as its own int8 file
(``models/trunk_head_int8.onnx``, output ``trunk_logits`` ``(1, 1, S/4, S/4)``) and exposes the
segmenter's ``mask_features`` as one more output of its file, run only when asked for.

Layers: a 3x3 conv, then 3x3 convs with dilations 2, 4 and 8 (about +-15 feature pixels, a
quarter of the input, of context: a trunk is told from a limb by what lies above and below it),
each with BatchNorm and ReLU, then a 1x1 conv to one logit.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from monodbh.models.modeling.common import dilated_body

__all__ = ["TrunkHeadConfig", "TrunkHead", "trunk_head_spec"]


@dataclass(frozen=True)
class TrunkHeadConfig:
    """``in_ch``: the segmenter's mask-feature width; ``ch``: the head's width; ``dilations``: one
    3x3 conv per entry."""

    in_ch: int = 128
    ch: int = 48
    dilations: tuple[int, ...] = (1, 2, 4, 8)


class TrunkHead(nn.Module):
    """Mask features ``(B, in_ch, h, w)`` -> trunk logits ``(B, 1, h, w)``.

    Examples
    --------
    >>> head = TrunkHead()
    >>> head(torch.zeros(2, 128, 64, 64)).shape
    torch.Size([2, 1, 64, 64])
    """

    def __init__(self, cfg: TrunkHeadConfig = TrunkHeadConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        self.body = dilated_body(cfg.in_ch, cfg.ch, cfg.dilations)
        self.out = nn.Conv2d(cfg.ch if cfg.dilations else cfg.in_ch, 1, 1)

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        if feats.ndim != 4 or feats.shape[1] != self.cfg.in_ch:
            raise ValueError(f"expected mask features (B, {self.cfg.in_ch}, h, w), got {tuple(feats.shape)}")
        return self.out(self.body(feats))


def trunk_head_spec(in_ch: int = 128, side: int = 64, threshold: float = 0.5, info: dict | None = None):
    """I/O contract of the trunk head's ONNX file (kind ``"trunk_head"``): the segmenter's
    ``mask_features`` ``(1, in_ch, side, side)`` in, ``trunk_logits`` ``(1, 1, side, side)`` out;
    ``extra``: ``trunk_threshold`` and ``info`` (its training and validation)."""
    from monodbh.models.modeling.registry import ModelSpec, TensorSpec
    return ModelSpec(
        kind="trunk_head", size="base",
        inputs=(TensorSpec("mask_features", (1, in_ch, side, side), "float32",
                           "the segmenter's mask features (its output of that name)"),),
        outputs=(TensorSpec("trunk_logits", (1, 1, side, side), "float32",
                            "trunk logit per pixel at the segmenter's mask resolution (a tree's stem "
                            "and the rope on it; not branches or foliage)"),),
        preprocess=(), metric="trunk_iou", higher_is_better=True,
        extra={"trunk_threshold": threshold, "info": info or {}})
