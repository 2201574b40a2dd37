"""The marker's thickness edge to edge: a blurred-box fit to its mean colour profile across the band.

Lives here: :func:`marker_thickness` (and its result :class:`MarkerThickness`). Imported by
:mod:`.ruler` (the rope or strap of known width as a ruler); imports numpy, cv2, scipy and the
band's sampling lines of :mod:`.profile`.

A round rope is lit on top and dark underneath and may carry a highlight along its length; a flat
strap is evenly lit; in sunlight either casts a shadow on the bark beside it. Profiles of the
colour perpendicular to the centre line, along the middle of the visible length, are averaged,
and each colour channel of the mean profile is fitted by a box (the marker, its interior linear
across it for the shading) blurred by a Gaussian (optics, JPEG's half-resolution colour) on a
linear background, with a blurred box on either side of it in the background's own colour, darker
(the shadow: the bark's hue kept, where the marker's shaded side keeps the marker's); the edges,
the blur and the shadow's widths are shared by the channels. Mixing is linear in the channels, so
the box's edges are the marker's silhouette to a small fraction of a pixel whatever the blur, the
shading and the shadow, where a half-maximum width of a chromaticity moves with them (decision
record ``docs/decisions/rope-ruler.md``).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .profile import band_cross_lines


__all__ = ["MarkerThickness", "marker_thickness", "blurred_box"]

_SQRT2 = np.sqrt(2.0)

#: a shadow narrower than this (pixels) beside the marker is none
SHADOW_MIN_PX = 0.05


@dataclass
class MarkerThickness:
    """The marker's thickness across its band.

    Attributes
    ----------
    width_px : edge-to-edge thickness perpendicular to the band (pixels of the image read).
    sigma_px : its 1-sigma: the spread of the same fit on four stretches along the band over
        sqrt(4) (an unresolved marker's stretches with the whole band's blur), at least the
        whole fit's own standard error.
    blur_px : the fitted Gaussian blur (1-sigma, pixels).
    contrast : the box's colour step against the background (norm of its three channels).
    n_columns : profiles averaged.
    resolved : the marker is wider than four blurs and three pixels, so that each edge is the
        colour gradient's own peak; a thinner one's width trades off against the blur in the
        fit (read less exactly).
    """
    width_px: float
    sigma_px: float
    blur_px: float
    contrast: float
    n_columns: int
    resolved: bool = False


def _phi(x):
    from scipy.special import erf
    return 0.5 * (1.0 + erf(x / _SQRT2))


def _box_moments(t: np.ndarray, t1: float, t2: float, s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``int_{t1}^{t2} u^k G_s(t - u) du`` for k = 0, 1, 2 (closed forms; ``G_s`` the Gaussian
    of 1-sigma ``s``)."""
    t = np.asarray(t, np.float64)
    z1, z2 = (t - t1) / s, (t - t2) / s
    D = _phi(z1) - _phi(z2)
    g1, g2 = np.exp(-0.5 * z1 ** 2) / np.sqrt(2 * np.pi), np.exp(-0.5 * z2 ** 2) / np.sqrt(2 * np.pi)
    M1 = t * D - s * (g2 - g1)
    M2 = t * t * D - 2 * t * s * (g2 - g1) + s * s * (D - (z1 * g1 - z2 * g2))
    return D, M1, M2


def blurred_box(t: np.ndarray, t1: float, t2: float, s: float, a: float = 1.0, c: float = 0.0,
                q: float = 0.0) -> np.ndarray:
    """A box from ``t1`` to ``t2`` of height ``a + c u + q u^2`` inside, convolved with a
    Gaussian of 1-sigma ``s`` (all in the units of ``t``).

    Parameters
    ----------
    t : (N,) positions.
    t1, t2 : the box's edges (``t1 < t2``); s : blur (> 0); a, c, q : its interior.

    Returns
    -------
    (N,) values.

    Examples
    --------
    >>> t = np.array([-10.0, 0.0, 2.0, 10.0])
    >>> np.round(blurred_box(t, -2.0, 2.0, 0.5), 3).tolist()     # half height at an edge
    [0.0, 1.0, 0.5, 0.0]
    """
    D, M1, M2 = _box_moments(t, t1, t2, s)
    return a * D + c * M1 + q * M2


def _profiles(rgb: np.ndarray, polyline: np.ndarray, thickness_px: float, inner: float, step_px: float):
    """``(off (M,), profiles (N, M, 3))``: the colour sampled across the band every 0.25 px at
    columns every ``step_px`` along the middle ``inner`` of the centre line; None when the line
    is too short or no column lies inside the image."""
    lines = band_cross_lines(polyline, rgb.shape[:2], inner=inner, step_px=step_px,
                             half_px=1.5 * max(float(thickness_px), 1.0) + 6.0, min_len_px=6.0)
    if lines is None:
        return None
    off, X, Y, (x0, y0, x1, y1) = lines
    keep = ((X >= 0) & (X <= x1 - x0 - 1) & (Y >= 0) & (Y <= y1 - y0 - 1)).all(1)
    if keep.sum() < 3:
        return None
    prof = cv2.remap(np.ascontiguousarray(rgb[y0:y1, x0:x1]).astype(np.float32), X, Y, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)
    return off, prof[keep]


def _basis(off: np.ndarray, t1: float, t2: float, s: float) -> np.ndarray:
    """(M, 4) columns: 1, t (the background), and the blurred box with its interior's constant
    and linear terms across it."""
    tc, h = 0.5 * (t1 + t2), max(0.5 * (t2 - t1), 1e-3)
    D, M1, _ = _box_moments(off, t1, t2, s)
    return np.stack([np.ones_like(off), off / max(abs(off[-1]), 1.0), D, (M1 - tc * D) / h], 1)


def _gradient_edges(off: np.ndarray, prof: np.ndarray, t1: float, t2: float, s: float,
                    shadow: tuple[float, float] = (0.0, 0.0)):
    """The outermost peaks of the colour gradient ``|d prof / dt|`` near the box's edges ``t1``,
    ``t2`` (sub-pixel: a parabola through the log of the peak, exact for a blurred step), or
    None where a side has no clear peak. On a side with a shadow (``shadow``: its widths before
    ``t1`` and after ``t2``, :func:`_fit`) the peak nearest the box's edge instead: the shadow's
    far edge is a gradient peak farther out."""
    dt = float(off[1] - off[0])
    g = np.sqrt((np.gradient(prof, dt, axis=0) ** 2).sum(1))
    gmax = float(g.max())
    if not gmax > 0:
        return None
    out = []
    for te, outward, w_sh in ((t1, -1, shadow[0]), (t2, +1, shadow[1])):
        win = np.flatnonzero(np.abs(off - te) <= 2 * s + 1.5)
        if len(win) < 3:
            return None
        strong = win[g[win] >= 0.3 * g[win].max()]
        # local maxima among the strong samples; the outermost one (the nearest to the edge
        # where a shadow lies beyond it)
        peaks = [i for i in strong if 0 < i < len(g) - 1 and g[i] >= g[i - 1] and g[i] >= g[i + 1]]
        if not peaks:
            return None
        if w_sh > SHADOW_MIN_PX:
            i = min(peaks, key=lambda k: abs(off[k] - te))
        else:
            i = min(peaks) if outward < 0 else max(peaks)
        la, lb, lc = np.log(np.maximum(g[i - 1:i + 2], 1e-9))
        den = la - 2 * lb + lc
        out.append(off[i] + (0.5 * (la - lc) / den * dt if den < 0 else 0.0))
    return (out[0], out[1]) if out[1] - out[0] > 0.3 else None


def _shade_columns(off: np.ndarray, t1: float, t2: float, s: float, w_lo: float, w_hi: float) -> np.ndarray:
    """(M, 2): blurred boxes ``w_lo`` wide before ``t1`` and ``w_hi`` wide after ``t2`` (the marker's
    shadow on the bark beside it; a column of zeros where its width is under
    :data:`SHADOW_MIN_PX`)."""
    z = np.zeros_like(off)
    return np.stack([_box_moments(off, t1 - w_lo, t1, s)[0] if w_lo > SHADOW_MIN_PX else z,
                     _box_moments(off, t2, t2 + w_hi, s)[0] if w_hi > SHADOW_MIN_PX else z], 1)


def _solve(off: np.ndarray, prof: np.ndarray, t1: float, t2: float, s: float, w_lo: float, w_hi: float,
           bg: np.ndarray):
    """The linear part of the model for given edges, blur and shadow widths: ``(coef (4, 3), shadow
    (M, 3), model (M, 3))``. Per channel a linear background and the blurred box with a linear
    interior (:func:`_basis`); beside it the shadow boxes (:func:`_shade_columns`), whose colour is
    the background's colour ``bg`` (3,) scaled, one factor per side shared by the channels: a
    shadow darkens the bark without changing its hue, where the marker's own shaded side keeps
    its colour. A side whose factor would brighten the bark has no shadow."""
    B = _basis(off, t1, t2, s)
    S = _shade_columns(off, t1, t2, s, w_lo, w_hi)
    # the channels share B and couple only through the shadow's factors: project B out, solve
    # for the factors on the background's colour direction, then each channel's coefficients
    C, *_ = np.linalg.lstsq(B, np.hstack([prof, S]), rcond=None)            # (4, 5)
    R = np.hstack([prof, S]) - B @ C
    z = R[:, :3] @ bg
    beta = np.zeros(2)
    on = np.array([w_lo > SHADOW_MIN_PX, w_hi > SHADOW_MIN_PX])
    while on.any():
        beta[:] = 0.0
        beta[on] = np.linalg.lstsq(R[:, 3:][:, on], z, rcond=None)[0]
        if not (beta > 0).any():
            break
        on &= beta <= 0             # a shadow darkens: a side that would brighten has none
    beta[~on] = 0.0
    shadow = (S @ beta)[:, None] * bg[None, :]
    coef = C[:, :3] - np.outer(C[:, 3:] @ beta, bg)
    return coef, shadow, B @ coef + shadow


def _fit(off: np.ndarray, prof: np.ndarray, T: float, blur: float | None = None,
         shadow: tuple[float, float] | None = None, start: tuple[float, float] | None = None):
    """Fit a blurred box with a linear interior on a linear background, and the marker's shadow
    beside it (:func:`_solve`), to each colour channel of the mean profile ``prof`` (M, 3), the
    edges, the blur and the shadow's widths shared (variable projection): ``(t1, t2, s, contrast,
    stderr of t2 - t1, resolved, (w_lo, w_hi))`` or None (``resolved``: see
    :class:`MarkerThickness`; ``w_lo``, ``w_hi``: the shadow's widths before ``t1`` and after
    ``t2``). With ``blur`` given, the blur is that (pixels, 1-sigma) and not fitted (no
    gradient-peak edges then: ``resolved`` is False); with ``shadow`` given, the shadow's widths
    are those; with ``start`` (``t1``, width), the fit starts there alone."""
    from scipy.optimize import least_squares

    tail = np.abs(off) > 0.5 * T + 2.5
    if tail.sum() < 8 or (~tail).sum() < 4:
        return None
    bg = np.median(prof[tail], axis=0)
    bg_unit = bg / max(float(np.linalg.norm(bg)), 1e-6)

    # parameters: t1, the width, then the blur and the shadow's widths where not given
    free = [True, True, blur is None, shadow is None, shadow is None]
    given = [0.0, 0.0, blur or 0.0] + list(shadow or (0.0, 0.0))

    def unpack(p):      # (t1, t2, s, w_lo, w_hi)
        v = np.array(given, np.float64)
        v[np.flatnonzero(free)] = p
        return v[0], v[0] + v[1], v[2], v[3], v[4]

    def resid(p):
        return (_solve(off, prof, *unpack(p), bg_unit)[2] - prof).ravel()

    # starts: where the colour departs most from the background's (the marker and its shadow),
    # and the rough thickness about the centre line
    dev = np.linalg.norm(prof - bg, axis=1)
    core = np.flatnonzero(dev > 0.5 * dev[~tail].max())
    starts = [(-0.5 * T, T, 0.5 * T, 0.5 * T)]
    if len(core) >= 2 and off[core[-1]] - off[core[0]] >= 0.5:
        starts.insert(0, (float(off[core[0]]), float(off[core[-1]] - off[core[0]]), 0.5, 0.5))
    if start is not None:
        starts = [(*start, 0.5, 0.5)]
    span = float(off[-1] - off[0])
    pick = np.flatnonzero(free)
    lo = np.array([off[0], 0.3, 0.15, 0.0, 0.0])[pick]
    hi = np.array([off[-1], span, max(3.0, 0.5 * T), span, span])[pick]
    scale = np.array([1.0, 1.0, 0.5, 1.0, 1.0])[pick]
    sol = None
    for t1_0, w_0, lo_0, hi_0 in starts:
        x0 = np.array([t1_0, w_0, 0.8, lo_0, hi_0])[pick]
        x0 = np.clip(x0, np.add(lo, 1e-6), np.subtract(hi, 1e-6))
        try:
            got = least_squares(resid, x0, bounds=(lo, hi), x_scale=scale, max_nfev=300, xtol=1e-5)
        except ValueError:
            continue
        if sol is None or got.cost < sol.cost:
            sol = got
    if sol is None:
        return None
    t1, t2, s, w_lo, w_hi = unpack(sol.x)
    if blur is not None:
        return t1, t2, s, float("nan"), float("nan"), False, (w_lo, w_hi)
    # a marker several blurs wide: its silhouette is the outermost colour-gradient peak on each
    # side near the fitted edge (a rope's shading and highlight make gradients inside it, not
    # outside), the nearest one on a side with a shadow (:func:`_gradient_edges`)
    resolved = False
    if t2 - t1 > 4 * s + 3:
        e = _gradient_edges(off, prof, t1, t2, s, (w_lo, w_hi))
        if e is not None:
            (t1, t2), resolved = e, True
    coef = _solve(off, prof, t1, t2, s, w_lo, w_hi, bg_unit)[0]
    contrast = float(np.linalg.norm(coef[2]))
    J = sol.jac
    dof = max(1, sol.fun.size - len(sol.x) - 14)
    s2 = float(np.sum(sol.fun ** 2)) / dof
    se = float(np.sqrt(max(np.linalg.pinv(J.T @ J)[1, 1] * s2, 0.0)))
    return t1, t2, s, contrast, se, resolved, (w_lo, w_hi)


def marker_thickness(rgb: np.ndarray, polyline: np.ndarray, thickness_px: float, *, inner: float = 0.7,
                     step_px: float = 0.5, pieces: int = 4) -> MarkerThickness | None:
    """The marker's (rope's or strap's) thickness edge to edge, to a fraction of a pixel.

    Parameters
    ----------
    rgb : (H, W, 3) uint8 image (undistorted) that holds the band.
    polyline : (N, 2) the band's centre line (x, y) in ``rgb``'s pixels, N >= 2.
    thickness_px : the band's rough thickness (sets the profiles' length).
    inner : the middle fraction of the centre line read (the ends fade round the stem).
    step_px : spacing of the profiles along the line.
    pieces : stretches along the line fitted apart for the uncertainty.

    Returns
    -------
    :class:`MarkerThickness`, or None where the band is too short or no box fits.

    Examples
    --------
    >>> m = marker_thickness(rgb, det.polyline, det.thickness_px)     # doctest: +SKIP
    >>> m.width_px, m.sigma_px                                        # doctest: +SKIP
    (12.43, 0.05)
    """
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"marker_thickness: expected an (H, W, 3) uint8 image, got {rgb.shape} {rgb.dtype}")
    if not np.isfinite(thickness_px) or thickness_px <= 0:
        raise ValueError(f"marker_thickness: need a positive rough thickness, got {thickness_px}")
    got = _profiles(rgb, polyline, thickness_px, inner, step_px)
    if got is None:
        return None
    off, prof = got
    fit = _fit(off, prof.mean(0), float(thickness_px))
    if fit is None:
        return None
    t1, t2, s, contrast, se, resolved, shadow = fit
    width = t2 - t1
    parts = []
    for chunk in np.array_split(np.arange(len(prof)), pieces):
        if len(chunk) >= 3:
            # the blur and the shadow are the whole band's (optics and JPEG, the light): the
            # stretches are fitted with them (a resolved marker's with its own blur), so that their
            # spread is the width's, not the width-blur-shadow trade-off's
            f = _fit(off, prof[chunk].mean(0), width, blur=None if resolved else s, shadow=shadow,
                     start=(t1, width))
            if f is not None:
                parts.append(f[1] - f[0])
    spread = float(np.std(parts, ddof=1) / np.sqrt(len(parts))) if len(parts) >= 2 else float("inf")
    return MarkerThickness(width_px=float(width), sigma_px=float(max(se, spread)), blur_px=float(s),
                           contrast=contrast, n_columns=int(len(prof)), resolved=bool(resolved))
