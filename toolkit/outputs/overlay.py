"""Overlay pictures of a measurement: what the pipeline saw and fitted, drawn on the photo.

The overlay is drawn from ``MeasureResult.debug``; every key is optional and a missing key is
simply not drawn. Keys the pipeline fills (contract between ``toolkit.pipeline`` and this
module):

``image``
    (H, W, 3) uint8 RGB picture the pipeline worked on (possibly downscaled and undistorted).
    When absent the photo is read from ``result.photo``.
``image_scale``
    float or ``(sx, sy)``: pixels of ``image`` per pixel of the photo (default 1.0). Used only to
    place ``result.rope_xy``, which is in photo pixels.

All pixel coordinates below are in **pixels of** ``image`` (the photo's pixels when there is
no ``image``), OpenCV pixel-centre convention:

``rope_polyline``
    (N, 2) float, the detected rope as a polyline (x, y).
``rope_xy``
    (2,) float, the rope centre (a cross; default ``result.rope_xy`` scaled by ``image_scale``).
``edges_xy``
    (2, 2) float, the left and right trunk edge points ``[[xl, yl], [xr, yr]]`` at the slice
    (joined by the slice line), or (2, K, 2): the left and right edge polylines.
``base_xy``
    (2,) float, the stem base that set the scale (traced, or tapped with ``--base``): a square
    marker joined to the rope centre by a dashed line (the 1.3 m the metrology used).
``slice_px``
    (M, 2) float, pixels of the breast-height slice (small dots), or (2, 2) the two ends of the
    slice line.
``tree_mask``
    (H, W) bool, the measured tree's pixels (outlined).
``vanishing``
    :class:`~monodbh.toolkit.vanishing.VerticalEstimate`; its ``segments`` (N, 4), the
    near-vertical lines that set "up", are drawn thin.
``slice_xy`` (alias ``slice_uv``)
    (M, 2) float metres, the slice's 3D points in the stem cross-section plane:
    column 0 across the view, column 1 along the view (away from the camera).
    Drawn in the inset with the camera at the bottom.
``circle``
    (3,) float metres, the fitted circle ``(cx, cy, r)`` in the same plane as ``slice_xy``.
``circles``
    optional dict name -> (cx, cy, r), other estimators' circles (thin grey lines in the inset).
``tree_cloud``
    :class:`~monodbh.toolkit.result.PointCloud` of the measured tree (written as a PLY by
    ``dbh measure --out-dir``; not drawn).

Also drawn: the text ``DBH 31.4 ± 1.2 cm``, the distance, the
scale source, the flags, or the error in red.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import numpy as np

from ..result import MeasureResult
from .atomic import atomic_path

__all__ = ["render_overlay", "write_overlay", "save_overlay", "format_dbh", "OVERLAY_MAX_SIDE"]

#: Longest side of an overlay picture; bigger images are downscaled.
OVERLAY_MAX_SIDE = 2048

_ROPE = (255, 40, 40)
_EDGE = (0, 220, 255)
_SLICE = (255, 230, 0)
_CIRCLE = (60, 255, 60)
_WHITE = (255, 255, 255)
_ERROR = (255, 70, 70)
_MASK = (120, 200, 255)
_UPLINE = (150, 150, 255)   # lines of the vertical vanishing point
_BASE = (255, 120, 0)       # the stem base that set the scale


def format_dbh(dbh_cm: Optional[float], sigma_cm: Optional[float], unicode: bool = True) -> str:
    """``"31.4 ± 1.2 cm"``; ``"31.4 cm"`` without sigma; ``"-"`` without a value."""
    if dbh_cm is None:
        return "-"
    if sigma_cm is None:
        return f"{dbh_cm:.1f} cm"
    return f"{dbh_cm:.1f} {'±' if unicode else '+/-'} {sigma_cm:.1f} cm"


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # pragma: no cover - Pillow < 10.1 or no FreeType
        return ImageFont.load_default()


def _arr(debug: dict, key: str, ndim_last: int = 2) -> Optional[np.ndarray]:
    v = debug.get(key)
    if v is None:
        return None
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    if a.size == 0 or a.shape[-1] != ndim_last or not np.all(np.isfinite(a)):
        return None
    return a


def _base_image(result: MeasureResult, image: Optional[np.ndarray]
                ) -> tuple[np.ndarray, float, tuple[float, float]]:
    """RGB image (H, W, 3) uint8, the factor applied to it here (downscaling) and its
    ``(sx, sy)`` scale relative to the photo."""
    dbg = result.debug or {}
    sc = dbg.get("image_scale", 1.0)
    try:
        sx, sy = (float(sc), float(sc)) if np.ndim(sc) == 0 else (float(sc[0]), float(sc[1]))
    except (TypeError, ValueError, IndexError):
        sx = sy = 1.0
    if image is None:
        image = dbg.get("image")
    if image is None:
        from monodbh.calib.photo import load_photo

        image = load_photo(result.photo)
        sx = sy = 1.0
    image = np.asarray(image)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    image = np.ascontiguousarray(image[..., :3]).astype(np.uint8)
    h, w = image.shape[:2]
    f = 1.0
    if max(h, w) > OVERLAY_MAX_SIDE:
        import cv2

        f = OVERLAY_MAX_SIDE / max(h, w)
        image = cv2.resize(image, (max(1, round(w * f)), max(1, round(h * f))),
                           interpolation=cv2.INTER_AREA)
    return image, f, (sx, sy)


def _to_img(xy: np.ndarray, s) -> np.ndarray:
    """Pixel coordinates scaled by ``s`` (pixel-centre convention) as int32 * 16 (4 bits)."""
    return np.rint((np.asarray(s) * (xy + 0.5) - 0.5) * 16).astype(np.int32)


def _pt(p) -> tuple[int, int]:
    return int(p[0]), int(p[1])


def _draw_geometry(img: np.ndarray, dbg: dict, result: MeasureResult, f: float,
                   photo_scale: tuple[float, float], lw: int) -> None:
    import cv2

    aa, sh = cv2.LINE_AA, 4  # 4 fractional bits
    mask = dbg.get("tree_mask")
    if mask is not None and np.ndim(mask) == 2 and np.any(mask):
        m = np.asarray(mask).astype(np.uint8)
        if m.shape[:2] != img.shape[:2]:
            m = cv2.resize(m, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_NEAREST)
        contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(img, contours, -1, _MASK, max(1, lw // 2), aa)
    vp = dbg.get("vanishing")
    seg = getattr(vp, "segments", None)
    if seg is not None and len(seg):
        # the near-vertical lines that set "up" (vertical vanishing point), thin
        for x1, y1, x2, y2 in np.asarray(seg, np.float64)[:400]:
            a, b = _to_img(np.array([[x1, y1], [x2, y2]]), f)
            cv2.line(img, _pt(a), _pt(b), _UPLINE, max(1, lw // 2), aa, sh)
    rope = _arr(dbg, "rope_polyline")
    if rope is not None and rope.ndim == 2 and len(rope) >= 2:
        cv2.polylines(img, [_to_img(rope, f)], False, _ROPE, lw + 1, aa, sh)
    edges = _arr(dbg, "edges_xy")
    if edges is not None:
        if edges.shape == (2, 2):
            ends = _to_img(edges, f)
            cv2.line(img, _pt(ends[0]), _pt(ends[1]), _SLICE, lw, aa, sh)
            for p in ends:
                cv2.circle(img, _pt(p), 5 * lw * 16, _EDGE, lw, aa, sh)
        elif edges.ndim == 3 and edges.shape[0] == 2:
            cv2.polylines(img, list(_to_img(edges, f)), False, _EDGE, lw, aa, sh)
    sl = _arr(dbg, "slice_px")
    if sl is not None and sl.ndim == 2:
        if len(sl) == 2:
            ends = _to_img(sl, f)
            cv2.line(img, _pt(ends[0]), _pt(ends[1]), _SLICE, lw, aa, sh)
        else:
            step = max(1, len(sl) // 2000)
            for p in _to_img(sl[::step], f):
                cv2.circle(img, _pt(p), max(1, lw // 2) * 16, _SLICE, -1, aa, sh)
    rxy = _arr(dbg, "rope_xy")
    if rxy is not None and rxy.shape == (2,):
        p = _to_img(rxy, f)
    elif result.rope_xy is not None and len(result.rope_xy) == 2:
        p = _to_img(np.asarray(result.rope_xy, np.float64), (f * photo_scale[0], f * photo_scale[1]))
    else:
        p = None
    if p is not None:
        d = 8 * lw * 16
        x, y = int(p[0]), int(p[1])
        cv2.line(img, (x - d, y - d), (x + d, y + d), _WHITE, lw, aa, sh)
        cv2.line(img, (x - d, y + d), (x + d, y - d), _WHITE, lw, aa, sh)
    base = _arr(dbg, "base_xy")
    if base is not None and base.shape == (2,) and np.isfinite(base).all():
        b = _to_img(base, f)
        d = 6 * lw * 16
        bx, by = int(b[0]), int(b[1])
        cv2.rectangle(img, (bx - d, by - d), (bx + d, by + d), _BASE, lw, aa, sh)
        if p is not None:
            # dashed line rope -> base
            n = 24
            for k in range(0, n, 2):
                a0 = (int(x + (bx - x) * k / n), int(y + (by - y) * k / n))
                a1 = (int(x + (bx - x) * (k + 1) / n), int(y + (by - y) * (k + 1) / n))
                cv2.line(img, a0, a1, _BASE, max(1, lw // 2), aa, sh)


def _inset(dbg: dict, size: int) -> Optional[np.ndarray]:
    """Square (size, size, 3) picture of the slice points and fitted circle(s), or None."""
    import cv2

    pts = _arr(dbg, "slice_xy")
    if pts is None:
        pts = _arr(dbg, "slice_uv")
    circ = _arr(dbg, "circle", 3)
    others = {k: np.asarray(v, np.float64) for k, v in (dbg.get("circles") or {}).items()
              if np.asarray(v).shape == (3,) and np.all(np.isfinite(v))}
    if pts is None and circ is None:
        return None
    boxes = []
    if pts is not None:
        boxes.append(np.c_[pts.min(0), pts.max(0)].T)
    for c in ([circ] if circ is not None else []) + list(others.values()):
        boxes.append(np.array([[c[0] - c[2], c[1] - c[2]], [c[0] + c[2], c[1] + c[2]]]))
    b = np.concatenate(boxes)
    lo, hi = b.min(0), b.max(0)
    centre, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 0.02) * 1.15
    panel = np.full((size, size, 3), 24, np.uint8)
    k = size / (2 * half)  # pixels per metre

    def to_px(u, v):  # across -> right, along the view -> up (camera at the bottom)
        return np.stack([(u - centre[0]) * k + size / 2, size / 2 - (v - centre[1]) * k], -1)

    aa, sh = cv2.LINE_AA, 4
    for c in others.values():
        cp = np.rint(to_px(c[0], c[1]) * 16).astype(int)
        cv2.circle(panel, tuple(cp), int(round(c[2] * k * 16)), (150, 150, 150), 1, aa, sh)
    if circ is not None:
        cp = np.rint(to_px(circ[0], circ[1]) * 16).astype(int)
        cv2.circle(panel, tuple(cp), int(round(circ[2] * k * 16)), _CIRCLE, 2, aa, sh)
        cv2.drawMarker(panel, tuple(int(v) for v in cp // 16), _CIRCLE, cv2.MARKER_CROSS, 8, 1)
    if pts is not None:
        step = max(1, len(pts) // 3000)
        for p in np.rint(to_px(pts[::step, 0], pts[::step, 1])).astype(int):
            cv2.circle(panel, tuple(p), 2, _SLICE, -1, aa)
    # 10 cm scale bar (5 cm for thin stems) and the camera direction
    bar = 0.10 if 0.10 * k <= size * 0.6 else 0.05
    y0, x0 = size - 12, 10
    cv2.line(panel, (x0, y0), (x0 + int(round(bar * k)), y0), _WHITE, 2)
    cv2.putText(panel, f"{bar * 100:.0f} cm", (x0, y0 - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                _WHITE, 1, aa)
    if size >= 220:
        cv2.putText(panel, "camera", (size - 62, size - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (180, 180, 180), 1, aa)
    cv2.rectangle(panel, (0, 0), (size - 1, size - 1), _WHITE, 1)
    return panel


def _text_lines(result: MeasureResult) -> list[tuple[str, tuple[int, int, int], bool]]:
    """(text, colour, big) lines of the caption."""
    if result.error:
        err = result.error if len(result.error) <= 90 else result.error[:87] + "..."
        return [("no measurement", _ERROR, True), (err, _ERROR, False)]
    lines = [("DBH " + format_dbh(result.dbh_cm, result.dbh_sigma_cm), _WHITE, True)]
    info = []
    if result.distance_m is not None:
        info.append(f"distance {result.distance_m:.2f} m")
    if result.scale_source:
        info.append(f"scale: {result.scale_source}")
    if info:
        lines.append(("   ".join(info), _WHITE, False))
    if result.flags:
        lines.append(("flags: " + ", ".join(map(str, result.flags)), (255, 200, 80), False))
    return lines


def render_overlay(result: MeasureResult, image: Optional[np.ndarray] = None) -> np.ndarray:
    """Draw the measurement of ``result`` on its photo.

    Parameters
    ----------
    result : MeasureResult
        With ``debug`` keys as documented in this module (all optional).
    image : (H, W, 3) uint8, optional
        RGB picture to draw on; default ``result.debug['image']`` or the photo file itself.
        Debug pixel coordinates must be in this image's pixels.

    Returns
    -------
    (H', W', 3) uint8
        RGB overlay; the size of the image drawn on, downscaled to at most
        :data:`OVERLAY_MAX_SIDE` pixels on the longest side.
    """
    from PIL import Image, ImageDraw

    dbg = result.debug or {}
    base, f, photo_scale = _base_image(result, image)
    img = base.copy()
    h, w = img.shape[:2]
    lw = max(1, round(max(h, w) / 800))
    _draw_geometry(img, dbg, result, f, photo_scale, lw)

    inset_size = max(96, min(h, w) // 3)
    panel = _inset(dbg, inset_size) if min(h, w) >= 128 else None
    if panel is not None:
        m = max(4, lw * 4)
        img[m:m + inset_size, w - m - inset_size:w - m] = panel

    pil = Image.fromarray(img)
    draw = ImageDraw.Draw(pil, "RGBA")
    big, small = max(14, round(min(h, w) / 14)), max(10, round(min(h, w) / 36))
    x, y = max(4, lw * 6), max(4, lw * 6)
    rows = [(t, c, _font(big if b else small)) for t, c, b in _text_lines(result)]
    boxes = [draw.textbbox((0, 0), t, font=f) for t, _, f in rows]
    bw = max(bx[2] for bx in boxes) + 2 * x
    bh = sum(bx[3] + small // 3 for bx in boxes) + 2 * y - x
    draw.rectangle((0, 0, min(w - 1, bw), min(h - 1, bh)), fill=(0, 0, 0, 150))
    for (t, c, f), bx in zip(rows, boxes):
        draw.text((x, y), t, font=f, fill=c)
        y += bx[3] + small // 3
    return np.asarray(pil)


def write_overlay(path: Any, result: MeasureResult, image: Optional[np.ndarray] = None) -> Path:
    """Render :func:`render_overlay` and write it as a PNG, atomically.

    Returns
    -------
    Path
        The written file.
    """
    return save_overlay(path, render_overlay(result, image))


def save_overlay(path: Any, rgb: np.ndarray) -> Path:
    """Write a rendered overlay (H, W, 3) uint8 RGB as a PNG, atomically; returns the path."""
    from PIL import Image

    p = Path(path)
    with atomic_path(p) as tmp:
        Image.fromarray(rgb).save(tmp, format="PNG", compress_level=3)
    return p
