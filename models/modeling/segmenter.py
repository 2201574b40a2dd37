"""Compact Mask2Former-style universal segmenter (kind ``"segmenter"``), our own implementation.

Paper (Li & Kan 2024, sec. 2.1) uses Mask2Former for tree instance masks; this is a laptop-sized
re-design of its three parts (Cheng et al. 2022):

1. **Backbone**: small ResNet-like CNN (stem stride 4, four stages at strides 4/8/16/32), or
   (size ``effl0``) an EfficientNet-Lite0 trunk (:mod:`.efficientnet_lite`).
2. **Pixel decoder**: FPN (lateral 1x1 + top-down nearest upsampling + 3x3 fusion) with a few
   plain transformer-encoder layers on the stride-32 tokens (instead of multi-scale deformable
   attention, which onnxruntime cannot run efficiently). Outputs ``mask_features`` at stride 4
   and three memory levels (strides 32, 16, 8).
3. **Transformer decoder**: learned queries (features + positional embeddings); each layer does
   masked cross-attention to one memory level (round robin, low resolution first), then
   self-attention, then FFN (post-norm). The attention mask of layer ``l`` is the sigmoid < 0.5
   region of the mask predicted from layer ``l - 1`` (average-pooled to the memory level), applied
   as an additive large negative float; rows that would be fully masked are unmasked
   (Mask2Former's guard). Class and mask predictions are made before the first layer and after
   each layer (deep supervision).

I/O (see :func:`segmenter_spec`): ``image`` (1, 3, S, S) float32 ImageNet-normalised ->
``class_logits`` (1, Q, C + 1) (last = no object) and ``mask_logits`` (1, Q, S/4, S/4).
Classes are indexed by the synthetic data's semantic ids: 0 sky, 1 ground, 2 other_vegetation,
3 tree (the only "thing" class), 4 other.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F

from monodbh.models.modeling.common import (NEG_INF, MLP, BasicBlock, ConvBNAct,
                                            sine_position_encoding)
from monodbh.models.modeling.efficientnet_lite import FEATURE_CHANNELS, EfficientNetLite0
from monodbh.models.modeling.registry import ModelSpec, Preprocess, TensorSpec, register

__all__ = ["CLASSES", "TREE_CLASS", "NO_OBJECT", "SegmenterConfig", "CONFIGS", "Segmenter",
           "segmenter_spec", "build_segmenter"]

CLASSES: tuple[str, ...] = ("sky", "ground", "other_vegetation", "tree", "other")
TREE_CLASS = 3
NO_OBJECT = len(CLASSES)  # index of the "no object" logit


@dataclass(frozen=True)
class SegmenterConfig:
    """Hyper-parameters of one size."""

    image_size: int
    channels: tuple[int, int, int, int]   #: backbone widths at strides 4, 8, 16, 32
    blocks: tuple[int, int, int, int]     #: BasicBlocks per stage
    hidden: int                            #: transformer / mask-feature width
    queries: int
    heads: int
    dec_layers: int
    dec_ffn: int
    enc_layers: int
    enc_ffn: int
    mask_mlp_layers: int = 3
    backbone: str = "resnet"                #: "resnet" (:class:`Backbone`) or "effl0" (pretrained)


CONFIGS: dict[str, SegmenterConfig] = {
    "tiny": SegmenterConfig(64, (8, 16, 24, 32), (1, 1, 1, 1), 32, 8, 2, 3, 64, 1, 64),
    # 64 queries: synthetic scenes show 40-60 trees of >= 64 px (at 256x256) plus 3-4 stuff masks
    "base": SegmenterConfig(256, (32, 64, 128, 192), (1, 2, 2, 2), 128, 64, 4, 6, 512, 2, 256),
    # the same network at a 384 x 384 input (thin stems: 1.5x the pixels across); see docs/TRAINING.md.
    # experiment, 900 steps from the "base" weights: held-out roped IoU 0.744 -> 0.755, PQ 0.41
    # -> 0.50, but benchmark DBH MAE 6.38 -> 6.75 cm; not shipped (docs/TRAINING.md)
    "base384": SegmenterConfig(384, (32, 64, 128, 192), (1, 2, 2, 2), 128, 64, 4, 6, 512, 2, 256),
    # the "base" head on an EfficientNet-Lite0 trunk whose ImageNet weights start the training
    # (real photos' bark and foliage; docs/TRAINING.md)
    "effl0": SegmenterConfig(256, FEATURE_CHANNELS, (0, 0, 0, 0), 128, 64, 4, 6, 512, 2, 256,
                             backbone="effl0"),
}


class Attention(nn.Module):
    """Multi-head attention with an optional additive bias ``(B, Nq, Nk)`` shared by heads.

    Written with plain Linear/MatMul/Softmax so it exports cleanly and is quantisable per part.
    """

    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.dh = dim // heads
        self.scale = self.dh ** -0.5
        self.q = nn.Linear(dim, dim)
        self.k = nn.Linear(dim, dim)
        self.v = nn.Linear(dim, dim)
        self.o = nn.Linear(dim, dim)

    def forward(self, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor,
                bias: torch.Tensor | None = None) -> torch.Tensor:
        B, Nq, D = q.shape
        Nk = k.shape[1]
        q = self.q(q).reshape(B, Nq, self.heads, self.dh).transpose(1, 2) * self.scale
        k = self.k(k).reshape(B, Nk, self.heads, self.dh).permute(0, 2, 3, 1)
        v = self.v(v).reshape(B, Nk, self.heads, self.dh).transpose(1, 2)
        scores = torch.matmul(q, k)  # (B, h, Nq, Nk)
        if bias is not None:
            scores = scores + bias.unsqueeze(1)
        attn = torch.softmax(scores, dim=-1)
        out = torch.matmul(attn, v).transpose(1, 2).reshape(B, Nq, D)
        return self.o(out)


class EncoderLayer(nn.Module):
    """Post-norm transformer encoder layer (self-attention with positional embedding + FFN)."""

    def __init__(self, dim: int, heads: int, ffn: int) -> None:
        super().__init__()
        self.attn = Attention(dim, heads)
        self.norm1 = nn.LayerNorm(dim)
        self.ffn = nn.Sequential(nn.Linear(dim, ffn), nn.ReLU(), nn.Linear(ffn, dim))
        self.norm2 = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        qk = x + pos
        x = self.norm1(x + self.attn(qk, qk, x))
        return self.norm2(x + self.ffn(x))


class DecoderLayer(nn.Module):
    """Mask2Former decoder layer: masked cross-attn -> self-attn -> FFN, post-norm."""

    def __init__(self, dim: int, heads: int, ffn: int) -> None:
        super().__init__()
        self.cross_attn = Attention(dim, heads)
        self.norm1 = nn.LayerNorm(dim)
        self.self_attn = Attention(dim, heads)
        self.norm2 = nn.LayerNorm(dim)
        self.ffn = nn.Sequential(nn.Linear(dim, ffn), nn.ReLU(), nn.Linear(ffn, dim))
        self.norm3 = nn.LayerNorm(dim)

    def forward(self, tgt: torch.Tensor, qpos: torch.Tensor, mem: torch.Tensor,
                mpos: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        tgt = self.norm1(tgt + self.cross_attn(tgt + qpos, mem + mpos, mem, bias))
        q = tgt + qpos
        tgt = self.norm2(tgt + self.self_attn(q, q, tgt))
        return self.norm3(tgt + self.ffn(tgt))


class Backbone(nn.Module):
    """ResNet-like CNN: ``(B, 3, S, S)`` -> features at strides 4, 8, 16, 32."""

    def __init__(self, channels: tuple[int, ...], blocks: tuple[int, ...]) -> None:
        super().__init__()
        c0 = channels[0]
        self.stem = nn.Sequential(ConvBNAct(3, max(c0 // 2, 8), 3, 2),
                                  ConvBNAct(max(c0 // 2, 8), c0, 3, 2))
        stages = []
        c_prev = c0
        for i, (c, n) in enumerate(zip(channels, blocks)):
            layers = [BasicBlock(c_prev, c, stride=1 if i == 0 else 2)]
            layers += [BasicBlock(c, c) for _ in range(n - 1)]
            stages.append(nn.Sequential(*layers))
            c_prev = c
        self.stages = nn.ModuleList(stages)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = self.stem(x)
        feats = []
        for stage in self.stages:
            x = stage(x)
            feats.append(x)
        return feats


class PixelDecoder(nn.Module):
    """FPN + transformer encoder on stride-32 tokens.

    Fusion after each top-down addition: 3x3 conv at stride 16, depthwise 3x3 + pointwise at
    strides 8 and 4 (a full 3x3 at stride 4 would cost more than the whole backbone).

    Returns ``mask_features`` (B, D, S/4, S/4) and memory maps at strides 32, 16, 8 (B, D, h, w).
    """

    def __init__(self, channels: tuple[int, ...], dim: int, heads: int, enc_layers: int,
                 enc_ffn: int) -> None:
        super().__init__()
        self.lateral = nn.ModuleList(ConvBNAct(c, dim, 1, act=None) for c in channels)
        # strides 4 and 8 (most pixels): depthwise-separable fusion; stride 16: full 3x3
        self.fuse = nn.ModuleList([
            nn.Sequential(ConvBNAct(dim, dim, 3, groups=dim), ConvBNAct(dim, dim, 1)),
            nn.Sequential(ConvBNAct(dim, dim, 3, groups=dim), ConvBNAct(dim, dim, 1)),
            ConvBNAct(dim, dim, 3)])
        self.encoder = nn.ModuleList(EncoderLayer(dim, heads, enc_ffn) for _ in range(enc_layers))
        self.mask_proj = nn.Conv2d(dim, dim, 1)
        self.dim = dim

    def forward(self, feats: list[torch.Tensor]) -> tuple[torch.Tensor, list[torch.Tensor]]:
        top = self.lateral[3](feats[3])
        B, D, h, w = top.shape
        if len(self.encoder):
            pos = sine_position_encoding(h, w, D, device=top.device).unsqueeze(0)
            t = top.flatten(2).transpose(1, 2)
            for layer in self.encoder:
                t = layer(t, pos)
            top = t.transpose(1, 2).reshape(B, D, h, w)
        outs = [top]
        x = top
        for i in (2, 1, 0):
            x = self.lateral[i](feats[i]) + F.interpolate(x, scale_factor=2.0, mode="nearest")
            x = self.fuse[i](x)
            outs.append(x)
        # outs: strides 32, 16, 8, 4
        return self.mask_proj(outs[3]), outs[:3]


class Segmenter(nn.Module):
    """The full network (see module docstring). ``forward(image) -> (class_logits, mask_logits)``."""

    def __init__(self, cfg: SegmenterConfig, num_classes: int = len(CLASSES)) -> None:
        super().__init__()
        self.cfg = cfg
        D = cfg.hidden
        self.num_classes = num_classes
        self.backbone = (EfficientNetLite0() if cfg.backbone == "effl0"
                         else Backbone(cfg.channels, cfg.blocks))
        self.pixel_decoder = PixelDecoder(cfg.channels, D, cfg.heads, cfg.enc_layers, cfg.enc_ffn)
        self.query_feat = nn.Embedding(cfg.queries, D)
        self.query_pos = nn.Embedding(cfg.queries, D)
        self.level_embed = nn.Embedding(3, D)
        self.layers = nn.ModuleList(DecoderLayer(D, cfg.heads, cfg.dec_ffn)
                                    for _ in range(cfg.dec_layers))
        self.decoder_norm = nn.LayerNorm(D)
        self.class_embed = nn.Linear(D, num_classes + 1)
        self.mask_embed = MLP(D, D, D, cfg.mask_mlp_layers)

    def _head(self, tgt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.decoder_norm(tgt)
        return self.class_embed(out), self.mask_embed(out)  # (B, Q, C+1), (B, Q, D)

    @staticmethod
    def _masks(emb: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        """Mask logits ``(B, Q, H, W)`` = mask embeddings ``(B, Q, D)`` . features ``(B, D, H, W)``."""
        B, D, H, W = feats.shape
        return torch.matmul(emb, feats.reshape(B, D, H * W)).reshape(B, -1, H, W)

    @staticmethod
    def _attn_bias(masks: torch.Tensor, stride: int) -> torch.Tensor:
        """Additive cross-attention bias ``(B, Q, h*w)`` from mask logits ``(B, Q, H, W)``.

        Keys where the average-pooled mask logit is < 0 (sigmoid < 0.5) get :data:`NEG_INF`;
        a query whose keys would all be masked attends everywhere (Mask2Former's guard).
        """
        m = masks.detach()
        if stride > 1:
            m = F.avg_pool2d(m, stride, stride)
        m = m.flatten(2)
        masked = (m < 0).to(m.dtype)                 # sigmoid < 0.5
        full = masked.min(dim=-1, keepdim=True)[0]   # 1 where every key is masked
        return masked * (1.0 - full) * NEG_INF

    def _decode(self, image: torch.Tensor, aux: bool
                ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        feats = self.backbone(image)
        mask_features, mems = self.pixel_decoder(feats)
        B = image.shape[0]
        H4 = mask_features.shape[2]
        memories, mposes, strides = [], [], []
        for lvl, m in enumerate(mems):
            _, D, h, w = m.shape
            memories.append(m.flatten(2).transpose(1, 2) + self.level_embed.weight[lvl])
            mposes.append(sine_position_encoding(h, w, D, device=m.device).unsqueeze(0))
            strides.append(H4 // h)
        # Inference: intermediate masks are only needed at the memory resolutions, and
        # avg_pool(emb . F) == emb . avg_pool(F) (linear), so pool the features once per level.
        pooled = None if aux else [F.avg_pool2d(mask_features, s, s) if s > 1 else mask_features
                                   for s in strides]
        qpos = self.query_pos.weight.unsqueeze(0).expand(B, -1, -1)
        tgt = self.query_feat.weight.unsqueeze(0).expand(B, -1, -1)
        preds: list[tuple[torch.Tensor, torch.Tensor]] = []
        n = len(self.layers)
        for i in range(n + 1):
            cls, emb = self._head(tgt)
            if aux or i == n:
                preds.append((cls, self._masks(emb, mask_features)))
            if i == n:
                break
            lvl = i % 3
            if aux:
                bias = self._attn_bias(preds[-1][1], strides[lvl])
            else:
                bias = self._attn_bias(self._masks(emb, pooled[lvl]), 1)
            tgt = self.layers[i](tgt, qpos, memories[lvl], mposes[lvl], bias)
        return preds

    def forward_all(self, image: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """All ``L + 1`` predictions ``(class_logits, mask_logits)`` (deep supervision); last = final."""
        return self._decode(image, aux=True)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``image`` (B, 3, S, S) -> ``class_logits`` (B, Q, C+1), ``mask_logits`` (B, Q, S/4, S/4).

        Same result as ``forward_all(image)[-1]`` without the full-resolution intermediate masks.
        """
        return self._decode(image, aux=False)[-1]


def segmenter_spec(size: str) -> ModelSpec:
    """I/O contract of the segmenter at ``size``."""
    cfg = CONFIGS[size]
    S, Q, M = cfg.image_size, cfg.queries, cfg.image_size // 4
    return ModelSpec(
        kind="segmenter", size=size,
        inputs=(TensorSpec("image", (1, 3, S, S), "float32",
                           "RGB photo resized (stretched) to SxS, /255, ImageNet mean/std"),),
        outputs=(TensorSpec("class_logits", (1, Q, len(CLASSES) + 1), "float32",
                            "per-query class logits; last index = no object"),
                 TensorSpec("mask_logits", (1, Q, M, M), "float32",
                            "per-query mask logits at 1/4 input resolution")),
        preprocess=(Preprocess(input="image"),),
        classes=CLASSES, metric="roped_iou", higher_is_better=True,
        extra={"no_object": NO_OBJECT, "tree_class": TREE_CLASS, "thing_classes": [TREE_CLASS],
               "stuff_classes": [c for c in range(len(CLASSES)) if c != TREE_CLASS],
               "num_queries": Q, "mask_stride": 4,
               # int8 export: keep attention scores/softmax/additive mask and the mask->bias
               # construction float (a -1e4 bias in an 8-bit range wipes out the scores)
               "quant_float_patterns": [r"attn/MatMul(_1)?$", r"attn/Add$", r"attn/Softmax$",
                                        r"attn/Mul$", r"^/(Less|Cast|ReduceMin|Sub)(_\d+)?$",
                                        r"^/Mul_\d+$"]},
    )


@register("segmenter", spec=segmenter_spec)
def build_segmenter(size: str) -> Segmenter:
    """Fresh segmenter of ``size`` (``"tiny"`` for tests, ``"base"`` for shipping)."""
    return Segmenter(CONFIGS[size])
