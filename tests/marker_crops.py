"""Synthetic crops of a red marker of known thickness across bark (tests of the marker readers).

:func:`marker_crop` draws a round rope (lit on top, dark underneath, a highlight along it) or a
flat strap at 8x supersampling, averages it down to exact sub-pixel edges, then blurs, adds noise
and JPEG-compresses it like a phone photo (4:2:0 colour).
"""
from __future__ import annotations

import cv2
import numpy as np

__all__ = ["marker_crop"]


def marker_crop(width_px: float, *, kind: str = "rope", blur_px: float = 0.8, jpeg_quality: int | None = 90,
                tilt_deg: float = 3.0, size=(200, 72), centre_y: float = 35.37, seed: int = 0,
                colour=(175, 28, 22), noise: float = 3.0, shadow_px: float = 0.0, shadow_factor: float = 0.55):
    """``(rgb (H, W, 3) uint8, polyline (2, 2))``: a marker ``width_px`` thick (perpendicular to
    its centre line, which ``polyline`` gives exactly) across a textured bark background; with
    ``shadow_px``, its shadow on the bark below it that wide (the bark darkened by
    ``shadow_factor``, its hue kept)."""
    rng = np.random.default_rng(seed)
    W, H = size
    S = 8
    yy, xx = np.mgrid[0:H * S, 0:W * S].astype(np.float64)
    xx, yy = (xx + 0.5) / S - 0.5, (yy + 0.5) / S - 0.5          # output-pixel coordinates
    a = np.radians(tilt_deg)
    cx = W / 2 - 0.5
    # signed distance across the band (positive downwards)
    d = (yy - centre_y) * np.cos(a) - (xx - cx) * np.sin(a)
    v = d / (width_px / 2)
    tex = cv2.resize(rng.normal(0, 1, (H // 2 + 1, W // 2 + 1)), (W * S, H * S), interpolation=cv2.INTER_CUBIC)
    bark = np.stack([112 + 14 * tex, 96 + 12 * tex, 80 + 10 * tex], -1)
    img = bark.copy()
    if shadow_px > 0:
        img[(d > width_px / 2) & (d <= width_px / 2 + shadow_px)] *= shadow_factor
    inside = np.abs(v) <= 1
    col = np.array(colour, np.float64)
    if kind == "rope":
        shade = 0.22 + 0.78 * np.clip((1 - v) / 2, 0, 1) ** 1.5       # lit top, dark underside
        hl = 90 * np.exp(-0.5 * ((v + 0.45) / 0.12) ** 2)             # a highlight along its length
        rope = col[None, None] * shade[..., None] + hl[..., None]
    elif kind == "strap":
        rope = col[None, None] * (0.85 + 0.05 * tex[..., None])
    else:
        raise ValueError(kind)
    img[inside] = rope[inside]
    img = cv2.resize(np.clip(img, 0, 255).astype(np.float32), (W, H), interpolation=cv2.INTER_AREA)
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    img = np.clip(img + rng.normal(0, noise, img.shape), 0, 255).astype(np.uint8)
    if jpeg_quality is not None:
        ok, buf = cv2.imencode(".jpg", img[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        img = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1].copy()
    dx = 0.45 * W
    p0 = np.array([cx - dx * np.cos(a), centre_y - dx * np.sin(a)])
    p1 = np.array([cx + dx * np.cos(a), centre_y + dx * np.sin(a)])
    return img, np.stack([p0, p1])
