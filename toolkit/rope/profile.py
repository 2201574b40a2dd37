"""The rope's thickness from its red-ness profile across the band; imported by the band
detector's refinement (:mod:`.band_refine`) and by the pipeline (the rope as a ruler).

:func:`profile_thickness` takes the median over columns of each column's full width at half
maximum; :func:`rope_profile_fwhm` averages the profiles along the rope first (the noise of dark
bark does not widen the half-maximum crossings of the mean profile).
"""
from __future__ import annotations

import cv2
import numpy as np

from .redness import redness_map

__all__ = ["profile_thickness", "rope_profile_fwhm", "band_cross_lines"]


def profile_thickness(F: np.ndarray, cols: np.ndarray, coef, x0: int, y0: int, T: float) -> float:
    """Median over columns of the FWHM (perpendicular to the band) of the red-ness profile.

    Parameters
    ----------
    F : (h, w) float32 red-ness of a window whose top-left pixel is ``(x0, y0)``.
    cols : window columns on the band; at most 60 of them are read.
    coef : polynomial centre line ``y(x)`` in image pixels (``np.polyval`` order).
    T : rough thickness, pixels (sets the profile's length and the peak's search range).

    Returns
    -------
    float : thickness, pixels (``T`` when no column has a peak).
    """
    Hh = F.shape[0]
    r = int(np.ceil(2 * T + 4))
    out = []
    dpoly = np.polyder(coef)
    for cc in cols[:: max(1, len(cols) // 60)]:
        yc = np.polyval(coef, cc + x0) - y0
        ya, yb = int(max(0, np.floor(yc - r))), int(min(Hh, np.ceil(yc + r) + 1))
        wdt = _column_fwhm(F[ya:yb, cc], np.arange(ya, yb) - yc, T)
        if wdt is not None:
            out.append(wdt * np.cos(np.arctan(np.polyval(dpoly, cc + x0))))
    return float(np.median(out)) if out else float(T)


def _column_fwhm(prof: np.ndarray, dy: np.ndarray, T: float):
    """Full width at half maximum of one column's profile ``prof`` (rows ``dy`` from the centre
    line) above its background; None when it has no peak."""
    if len(prof) < 5:
        return None
    inner = np.abs(dy) <= T / 2 + 1
    if not inner.any() or inner.all():
        return None
    bg = float(np.median(prof[~inner]))
    pk = float(prof[inner].max())
    if pk - bg <= 1e-3:
        return None
    above = prof > bg + 0.5 * (pk - bg)
    # the run containing the peak
    ip = int(np.flatnonzero(inner)[np.argmax(prof[inner])])
    a = ip
    while a > 0 and above[a - 1]:
        a -= 1
    b = ip
    while b < len(prof) - 1 and above[b + 1]:
        b += 1
    # sub-pixel edges by linear interpolation
    half = bg + 0.5 * (pk - bg)

    def edge(i_in, i_out):
        if i_out < 0 or i_out >= len(prof):
            return float(i_in)
        v_in, v_out = prof[i_in], prof[i_out]
        t = (v_in - half) / max(v_in - v_out, 1e-6)
        return i_in + t * (i_out - i_in)

    return edge(b, b + 1) - edge(a, a - 1)


def rope_profile_fwhm(rgb: np.ndarray, polyline: np.ndarray, thickness_px: float, *,
                      inner: float = 0.6) -> tuple[float, float]:
    """The rope's thickness from its mean red-ness profile across the band.

    Each column along the rope's centre line (its middle ``inner`` fraction) gives a profile
    across the band; the profiles, aligned on the centre line, are averaged (so that the noise
    of dark bark does not widen the half-maximum crossings), and the full width at half maximum
    of the mean profile above its background is returned.

    Parameters
    ----------
    rgb : (H, W, 3) uint8 photo.
    polyline : (N, 2) rope centre line (x, y) pixels.
    thickness_px : rough thickness (sets the sampling window).
    inner : fraction of the rope's length used, centred.

    Returns
    -------
    (fwhm_px, contrast): the width (pixels, perpendicular to the rope; nan when there is no peak)
    and the peak's red-ness above the background.

    Examples
    --------
    >>> fwhm, contrast = rope_profile_fwhm(rgb, det.polyline, det.thickness_px)   # doctest: +SKIP
    """
    T = max(float(thickness_px), 1.0)
    lines = band_cross_lines(polyline, rgb.shape[:2], inner=inner, step_px=1.0, half_px=3.0 * T + 4.0,
                             min_len_px=4.0)
    if lines is None:
        return float("nan"), 0.0
    off, X, Y, (x0, y0, x1, y1) = lines
    F = redness_map(np.ascontiguousarray(rgb[y0:y1, x0:x1]))
    prof = cv2.remap(F, X, Y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).mean(0)
    return _mean_profile_fwhm(prof, off, T)


def _mean_profile_fwhm(prof: np.ndarray, off: np.ndarray, T: float) -> tuple[float, float]:
    """``(fwhm, contrast)`` of a mean profile ``prof`` sampled at offsets ``off`` (pixels)."""
    tail = np.abs(off) > 1.5 * T + 2
    bg = float(np.median(prof[tail]))
    core = ~tail
    ip = int(np.flatnonzero(core)[np.argmax(prof[core])])
    pk = float(prof[ip])
    if pk - bg <= 1e-3:
        return float("nan"), 0.0
    half = bg + 0.5 * (pk - bg)
    a = ip
    while a > 0 and prof[a - 1] > half:
        a -= 1
    b = ip
    while b < len(prof) - 1 and prof[b + 1] > half:
        b += 1
    if a == 0 or b == len(prof) - 1:
        return float("nan"), pk - bg

    def cross(i_in, i_out):
        v_in, v_out = prof[i_in], prof[i_out]
        return off[i_in] + (v_in - half) / max(v_in - v_out, 1e-9) * (off[i_out] - off[i_in])

    return float(cross(b, b + 1) - cross(a, a - 1)), pk - bg


def band_cross_lines(polyline: np.ndarray, shape: tuple[int, int], *, inner: float, step_px: float,
                     half_px: float, min_len_px: float):
    """Sampling lines across a band: perpendicular to its centre line, every ``step_px`` along
    the middle ``inner`` fraction of it, from ``-half_px`` to ``half_px`` every 0.25 px.

    Parameters
    ----------
    polyline : (N, 2) the band's centre line (x, y) pixels.
    shape : ``(H, W)`` of the image to be sampled.
    inner, step_px, half_px : as above; min_len_px : shorter centre lines give None.

    Returns
    -------
    ``(off (M,), X (K, M), Y (K, M), (x0, y0, x1, y1))``: the offsets across the band and the
    float32 sample coordinates for :func:`cv2.remap` in the window ``[y0:y1, x0:x1]`` of the
    image (which holds every line, clipped to the image); None when the line is too short or the
    window is empty.
    """
    P = np.asarray(polyline, np.float64)
    if P.ndim != 2 or P.shape[1] != 2 or len(P) < 2:
        return None
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    L = float(s[-1])
    if L < min_len_px:
        return None
    ss = np.arange(0.5 * (1 - inner) * L, 0.5 * (1 + inner) * L, step_px)
    cx, cy = np.interp(ss, s, P[:, 0]), np.interp(ss, s, P[:, 1])
    k = np.clip(np.searchsorted(s, ss) - 1, 0, len(P) - 2)
    t = (P[k + 1] - P[k]) / np.maximum(seg[k], 1e-9)[:, None]
    n = np.stack([-t[:, 1], t[:, 0]], 1)
    r = float(half_px)
    off = np.arange(-r, r + 1e-6, 0.25)
    H, W = shape
    x0, x1 = int(max(0, np.floor(cx.min() - r - 2))), int(min(W, np.ceil(cx.max() + r + 3)))
    y0, y1 = int(max(0, np.floor(cy.min() - r - 2))), int(min(H, np.ceil(cy.max() + r + 3)))
    if x1 - x0 < 3 or y1 - y0 < 3:
        return None
    X = (cx[:, None] + off[None] * n[:, :1] - x0).astype(np.float32)
    Y = (cy[:, None] + off[None] * n[:, 1:] - y0).astype(np.float32)
    return off, X, Y, (x0, y0, x1, y1)
