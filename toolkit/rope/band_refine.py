"""The band detector's full-resolution refinement of a chosen band: its mask, centre line,
thickness and middle; imported by :mod:`.band`.

The band found on the working copy is read again at full resolution in a small window around
it: the thin-line contrast there gives the band's pixels, a weighted quadratic (or linear) fit
of their column centres the centre line, the full width at half maximum of the red-ness profile
across the band the thickness (:func:`.profile.profile_thickness`), and with a tree mask the
middle of the trunk's run along the band the centre.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .detection import RopeCandidate
from .geometry import trunk_run
from .profile import profile_thickness
from .redness import line_contrast, redness_map

__all__ = ["RefinedBand", "refine_band"]


@dataclass(frozen=True)
class RefinedBand:
    """A band read at full resolution (pixels of the photo).

    Attributes
    ----------
    center_xy : (x, y) the band's middle (the trunk's, with a tree mask); direction : unit
    (dx, dy) there; polyline : (N, 2) float32 centre line; thickness_px : across the band;
    mask : (H, W) bool band pixels.
    """
    center_xy: tuple[float, float]
    direction: tuple[float, float]
    polyline: np.ndarray = field(repr=False)
    thickness_px: float
    mask: np.ndarray = field(repr=False)


def refine_band(rgb: np.ndarray, c: RopeCandidate, tree_mask: np.ndarray | None) -> RefinedBand:
    """Full-resolution band mask, centre line and thickness around candidate ``c``.

    Parameters
    ----------
    rgb : (H, W, 3) uint8 photo; c : candidate in its pixels; tree_mask : (H, W) bool or None.
    """
    H, W = rgb.shape[:2]
    T = max(c.thickness_px, 1.0)
    x0, x1, y0, y1 = _window(c, T, H, W)
    F = redness_map(rgb[y0:y1, x0:x1])
    d = max(2, int(round(0.5 * T + 1.5)))
    R = line_contrast(F, ds=(d, d + 1), sigma_x=float(np.clip(0.5 * T, 1.0, 4.0)),
                      sigma_y=float(np.clip(0.2 * T, 0.5, 3.0)))
    xs = np.arange(x0, x1, dtype=np.float32)
    yy = np.arange(y0, y1, dtype=np.float32)[:, None]
    m = _band_pixels(R, c, xs, yy, T)
    cols = np.flatnonzero(m.any(0))
    coef = None
    poly = c.polyline.copy()
    thick = c.thickness_px
    if len(cols) >= 3:
        coef, cols, poly = _fit_centre_line(R, m, cols, xs, yy, T)
        # thickness: full width at half maximum of the red-ness profile across the band
        thick = profile_thickness(F, cols, coef, x0, y0, T)
        mm = np.zeros_like(m)
        mm[:, cols] = m[:, cols]
        m = mm
    mask = np.zeros((H, W), bool)
    mask[y0:y1, x0:x1] = m
    center, direction = _middle(poly, coef, c, tree_mask)
    return RefinedBand(center_xy=center, direction=direction, polyline=poly, thickness_px=float(thick), mask=mask)


def _window(c: RopeCandidate, T: float, H: int, W: int) -> tuple[int, int, int, int]:
    """``(x0, x1, y0, y1)``: the candidate's bounding box padded by ``3 T + 8``, in the image."""
    pad = int(np.ceil(3 * T + 8))
    x0 = max(0, int(np.floor(c.polyline[:, 0].min())) - pad)
    x1 = min(W, int(np.ceil(c.polyline[:, 0].max())) + pad + 1)
    y0 = max(0, int(np.floor(c.polyline[:, 1].min())) - pad)
    y1 = min(H, int(np.ceil(c.polyline[:, 1].max())) + pad + 1)
    return x0, x1, y0, y1


def _band_pixels(R: np.ndarray, c: RopeCandidate, xs: np.ndarray, yy: np.ndarray, T: float) -> np.ndarray:
    """(h, w) bool: window pixels near the candidate's centre line whose contrast is part of the band."""
    yc = np.interp(xs, c.polyline[:, 0], c.polyline[:, 1]).astype(np.float32)
    band = np.abs(yy - yc[None, :]) <= (T + 3)
    band &= ((xs >= c.polyline[0, 0] - 0.05 * c.length_px - 2) & (xs <= c.polyline[-1, 0] + 0.05 * c.length_px + 2))[None, :]
    vals = R[band]
    thr = max(0.4 * float(np.percentile(vals, 97)) if vals.size else 0.0, 0.01)
    m = band & (R > thr)
    # keep columns whose response is part of the band (drop isolated specks)
    colmax = np.where(m, R, 0).max(0)
    m &= (colmax > 1.5 * thr)[None, :]
    return m


def _fit_centre_line(R, m, cols, xs, yy, T):
    """``(coef, cols, polyline)``: the band's centre line fitted through the contrast-weighted
    column centres (outlier columns dropped), the columns kept, and the line sampled every 2 px."""
    w = np.where(m, R, 0)
    ws = w.sum(0)
    ymean = (w * yy).sum(0) / np.maximum(ws, 1e-9)
    xv, yv = xs[cols], ymean[cols]
    # a quadratic only where the columns cover the band (a wide strap read with too thin a
    # line filter gives columns near its ends only, and a quadratic through those sags at will)
    covered = len(cols) / max(1.0, float(cols.max() - cols.min() + 1))
    deg = 2 if len(cols) > 12 and covered >= 0.5 else 1
    coef = np.polyfit(xv, yv, deg, w=np.sqrt(ws[cols]))
    res = yv - np.polyval(coef, xv)
    good = np.abs(res) < max(2.0, 0.75 * T)
    if good.sum() >= 3 and not good.all():
        coef = np.polyfit(xv[good], yv[good], deg, w=np.sqrt(ws[cols][good]))
        cols = cols[good]
        xv = xv[good]
    xl, xr = float(xv.min()), float(xv.max())
    px = np.linspace(xl, xr, max(2, int(xr - xl) // 2 + 1))
    py = np.polyval(coef, px)
    return coef, cols, np.stack([px, py], 1).astype(np.float32)


def _middle(poly, coef, c: RopeCandidate, tree_mask):
    """``(center_xy, direction)`` of the refined band: the middle of its extent (of the trunk's
    run along it, with a tree mask) and the unit tangent there."""
    xc = 0.5 * (poly[0, 0] + poly[-1, 0])
    if tree_mask is not None:
        l, r = trunk_run(tree_mask, poly, xc)
        if r >= l:
            xc = 0.5 * (l + r)
    if coef is not None:
        yc0 = float(np.polyval(coef, xc))
        slope = float(np.polyval(np.polyder(coef), xc))
    else:
        yc0 = float(np.interp(xc, poly[:, 0], poly[:, 1]))
        slope = c.direction[1] / max(c.direction[0], 1e-6)
    dvec = np.array([1.0, slope]) / np.hypot(1.0, slope)
    return (float(xc), yc0), (float(dvec[0]), float(dvec[1]))
