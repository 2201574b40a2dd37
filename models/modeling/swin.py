"""Export-friendly Swin Transformer encoder (Liu et al. 2021), fixed input size.

Everything that depends on the spatial layout (window partition sizes, the relative position
index, the shifted-window attention masks) is computed once in ``__init__`` from python ints and
stored as buffers, so a traced graph contains only fixed-shape Reshape/Transpose/MatMul/Softmax
ops (ONNX opset 17, int8-quantizable MatMuls).  Reshapes use ``-1`` for the batch axis only, so
the same module trains with any batch size and exports with batch 1.

Tokens are kept channels-last, ``(B, H, W, C)``; the encoder returns NCHW feature maps.
"""
from __future__ import annotations

import torch
from torch import nn

__all__ = ["WindowAttention", "SwinBlock", "PatchEmbed", "PatchMerging", "SwinStage", "SwinEncoder"]


def _relative_position_index(ws: int) -> torch.Tensor:
    """Index into the ``((2 ws - 1)^2, heads)`` bias table, ``(ws*ws, ws*ws)`` int64."""
    coords = torch.stack(torch.meshgrid(torch.arange(ws), torch.arange(ws), indexing="ij")).flatten(1)
    rel = (coords[:, :, None] - coords[:, None, :]).permute(1, 2, 0) + (ws - 1)
    return rel[:, :, 0] * (2 * ws - 1) + rel[:, :, 1]


def _shift_attention_mask(h: int, w: int, ws: int, shift: int) -> torch.Tensor:
    """Additive mask ``(nW, ws*ws, ws*ws)`` for shifted windows (0 or -100)."""
    img = torch.zeros(h, w)
    cnt = 0
    sl = (slice(0, -ws), slice(-ws, -shift), slice(-shift, None))
    for hs in sl:
        for wsl in sl:
            img[hs, wsl] = cnt
            cnt += 1
    win = img.view(h // ws, ws, w // ws, ws).permute(0, 2, 1, 3).reshape(-1, ws * ws)
    diff = win[:, None, :] - win[:, :, None]
    return torch.where(diff != 0, torch.tensor(-100.0), torch.tensor(0.0))


class WindowAttention(nn.Module):
    """Multi-head self attention inside ``ws x ws`` windows with relative position bias.

    Input ``(B*nW, N, C)`` with ``N = ws*ws``; optional additive mask ``(nW, N, N)`` buffer is
    supplied by the caller (``SwinBlock``).
    """

    def __init__(self, dim: int, ws: int, heads: int):
        super().__init__()
        self.dim, self.ws, self.heads = dim, ws, heads
        self.scale = (dim // heads) ** -0.5
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        self.bias_table = nn.Parameter(torch.zeros((2 * ws - 1) ** 2, heads))
        nn.init.trunc_normal_(self.bias_table, std=0.02)
        self.register_buffer("rel_index", _relative_position_index(ws).flatten(), persistent=False)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        n, c, h = self.ws * self.ws, self.dim, self.heads
        qkv = self.qkv(x).reshape(-1, n, 3, h, c // h).permute(2, 0, 3, 1, 4)
        q, k, v = qkv[0], qkv[1], qkv[2]                                  # (B', h, N, d)
        attn = torch.matmul(q * self.scale, k.transpose(-2, -1))          # (B', h, N, N)
        bias = self.bias_table[self.rel_index].reshape(n, n, h).permute(2, 0, 1)
        attn = attn + bias.unsqueeze(0)
        if mask is not None:
            nw = mask.shape[0]
            attn = attn.reshape(-1, nw, h, n, n) + mask.unsqueeze(1).unsqueeze(0)
            attn = attn.reshape(-1, h, n, n)
        attn = torch.softmax(attn, dim=-1)
        out = torch.matmul(attn, v).transpose(1, 2).reshape(-1, n, c)
        return self.proj(out)


class SwinBlock(nn.Module):
    """(Shifted) window attention + MLP, pre-norm residual.  Works on ``(B, H, W, C)``."""

    def __init__(self, dim: int, resolution: tuple[int, int], heads: int, ws: int = 8,
                 shift: bool = False, mlp_ratio: float = 4.0):
        super().__init__()
        h, w = resolution
        ws = min(ws, h, w)
        if h % ws or w % ws:
            raise ValueError(f"resolution {resolution} not divisible by window {ws}")
        self.h, self.w, self.ws, self.dim = h, w, ws, dim
        # No shift when a single window covers the map (as in the reference implementation).
        self.shift = ws // 2 if (shift and min(h, w) > ws) else 0
        self.norm1 = nn.LayerNorm(dim)
        self.attn = WindowAttention(dim, ws, heads)
        self.norm2 = nn.LayerNorm(dim)
        hidden = int(dim * mlp_ratio)
        self.mlp = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, dim))
        if self.shift:
            self.register_buffer("attn_mask", _shift_attention_mask(h, w, ws, self.shift), persistent=False)
        else:
            self.attn_mask = None

    def _partition(self, x: torch.Tensor) -> torch.Tensor:
        h, w, ws, c = self.h, self.w, self.ws, self.dim
        x = x.reshape(-1, h // ws, ws, w // ws, ws, c).permute(0, 1, 3, 2, 4, 5)
        return x.reshape(-1, ws * ws, c)

    def _merge(self, x: torch.Tensor) -> torch.Tensor:
        h, w, ws, c = self.h, self.w, self.ws, self.dim
        x = x.reshape(-1, h // ws, w // ws, ws, ws, c).permute(0, 1, 3, 2, 4, 5)
        return x.reshape(-1, h, w, c)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, H, W, C) -> (B, H, W, C)``."""
        y = self.norm1(x)
        if self.shift:
            y = torch.roll(y, shifts=(-self.shift, -self.shift), dims=(1, 2))
        y = self._merge(self.attn(self._partition(y), self.attn_mask))
        if self.shift:
            y = torch.roll(y, shifts=(self.shift, self.shift), dims=(1, 2))
        x = x + y
        return x + self.mlp(self.norm2(x))


class PatchEmbed(nn.Module):
    """``(B, Cin, H, W) -> (B, H/p, W/p, C)``: stride-p convolution + LayerNorm."""

    def __init__(self, in_ch: int, dim: int, patch: int = 4):
        super().__init__()
        self.proj = nn.Conv2d(in_ch, dim, patch, stride=patch)
        self.norm = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.norm(self.proj(x).permute(0, 2, 3, 1))


class PatchMerging(nn.Module):
    """2x2 neighbourhood concat + LayerNorm + Linear: ``(B, H, W, C) -> (B, H/2, W/2, out)``.

    The four strided slices of the reference implementation are written as one
    reshape/transpose (fixed shapes, no Slice ops).
    """

    def __init__(self, dim: int, resolution: tuple[int, int], out_dim: int | None = None):
        super().__init__()
        self.h, self.w, self.dim = resolution[0], resolution[1], dim
        self.norm = nn.LayerNorm(4 * dim)
        self.reduction = nn.Linear(4 * dim, out_dim or 2 * dim, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w, c = self.h, self.w, self.dim
        x = x.reshape(-1, h // 2, 2, w // 2, 2, c).permute(0, 1, 3, 4, 2, 5)
        x = x.reshape(-1, h // 2, w // 2, 4 * c)
        return self.reduction(self.norm(x))


class SwinStage(nn.Module):
    """``depth`` Swin blocks alternating regular / shifted windows at one resolution."""

    def __init__(self, dim: int, resolution: tuple[int, int], depth: int, heads: int, ws: int,
                 mlp_ratio: float = 4.0):
        super().__init__()
        self.blocks = nn.ModuleList(
            SwinBlock(dim, resolution, heads, ws, shift=bool(i % 2), mlp_ratio=mlp_ratio)
            for i in range(depth))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for blk in self.blocks:
            x = blk(x)
        return x


class SwinEncoder(nn.Module):
    """Hierarchical Swin encoder.

    ``PatchEmbed(patch)`` then ``len(depths)`` stages; stage ``i`` runs at stride
    ``patch * 2**i`` with ``embed * 2**i`` channels; a ``PatchMerging`` precedes every stage but
    the first, and ``extra_merges`` further mergings (no attention blocks) follow the last stage.

    Parameters
    ----------
    in_ch, img_size : input channels and (H, W) (fixed; divisible by ``patch * 2**(stages-1) * ws``
        where windows are used).
    embed, depths, heads, ws, mlp_ratio : usual Swin hyper-parameters.

    ``forward(x (B, in_ch, H, W))`` returns a list of NCHW maps, one per stride
    ``patch * 2**j`` for ``j = 0 .. len(depths) - 1 + extra_merges``; ``self.channels`` and
    ``self.strides`` describe them.
    """

    def __init__(self, in_ch: int = 4, img_size: tuple[int, int] = (256, 256), embed: int = 48,
                 depths: tuple[int, ...] = (2, 2, 2, 2), heads: tuple[int, ...] = (2, 4, 8, 16),
                 ws: int = 8, patch: int = 4, mlp_ratio: float = 4.0, extra_merges: int = 1):
        super().__init__()
        h, w = img_size[0] // patch, img_size[1] // patch
        self.patch_embed = PatchEmbed(in_ch, embed, patch)
        self.merges = nn.ModuleList()
        self.stages = nn.ModuleList()
        self.norms = nn.ModuleList()
        self.channels: list[int] = []
        self.strides: list[int] = []
        dim, stride = embed, patch
        for i, d in enumerate(depths):
            if i > 0:
                self.merges.append(PatchMerging(dim, (h, w)))
                dim, h, w, stride = dim * 2, h // 2, w // 2, stride * 2
            self.stages.append(SwinStage(dim, (h, w), d, heads[i], ws, mlp_ratio))
            self.norms.append(nn.LayerNorm(dim))
            self.channels.append(dim)
            self.strides.append(stride)
        self.extra = nn.ModuleList()
        for _ in range(extra_merges):
            self.extra.append(PatchMerging(dim, (h, w)))
            self.norms.append(nn.LayerNorm(dim * 2))
            dim, h, w, stride = dim * 2, h // 2, w // 2, stride * 2
            self.channels.append(dim)
            self.strides.append(stride)
        self.apply(self._init)

    @staticmethod
    def _init(m: nn.Module) -> None:
        if isinstance(m, nn.Linear):
            nn.init.trunc_normal_(m.weight, std=0.02)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.LayerNorm):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        feats = []
        t = self.patch_embed(x)
        k = 0
        for i, stage in enumerate(self.stages):
            if i > 0:
                t = self.merges[i - 1](t)
            t = stage(t)
            feats.append(self.norms[k](t).permute(0, 3, 1, 2))
            k += 1
        for m in self.extra:
            t = m(t)
            feats.append(self.norms[k](t).permute(0, 3, 1, 2))
            k += 1
        return feats
