"""Classical detection of the red measuring rope tied around a stem at breast height.

The rope is a thin, red, roughly horizontal band (an ellipse arc of a ring seen from slightly
above or below) that crosses a trunk from edge to edge. Detection, without a learned model:

1. **Red-ness** ``F = max(0, R - max(G, B) - max(G - B, 0) / 2) / (R + G + B + 30)``: a chromaticity, so
   shading and exposure change it little; the ``G - B`` term lowers orange (sandy ground,
   flagging tape). Computed on a copy downscaled to ``work_long_side`` pixels and two pyramid
   levels below it (thick ropes).
2. **Thin-line contrast** (:func:`line_contrast`): after a blur along x, the red-ness of a pixel
   minus the larger of the red-ness ``d`` pixels above and below it. It is in red-ness units at
   every scale, is zero on the edges of red blobs and on evenly reddish bark, and answers to bands
   up to ~60 deg from horizontal, so vertical paint marks and hanging rope ends give little.
3. **Pieces and bands**: connected components of the contrast map described by moments;
   pieces that extrapolate into each other (a rope behind a branch or a thin stem, a knot) are
   linked end to end; runs of linked pieces are fitted with a quadratic centre line. The
   ``max_candidates`` best runs by a cheap band score get the full score, plus up to half as many
   from image squares none of those occupies (:func:`_diverse`): a patch of red clutter (leaf
   litter, berries) would otherwise take the whole budget from a faint rope elsewhere.
4. **Score** (log-odds, :data:`SCORE_WEIGHTS`, fitted on synthetic photos plus rope-free real
   photos; see :func:`candidate_features`): contrast, redness, length, continuity, thinness,
   red (not orange) hue, fit residual, red clutter and red area around the band, evenness along
   it, whether both band ends sit on a vertical intensity edge (the trunk silhouette) that holds
   above and below the band, and whether the surface above the band matches the one below (one
   trunk face, not a horizon between two trunks). Hard gates: length >= 5 x thickness, hue
   ``(G - B) / R <= 0.35``. With a ``tree_mask``, bands that lie on the mask and span the trunk's
   width there are preferred.
5. **Decision**: the best band scoring above ``min_score``; a rival within ``ambiguity_margin``
   makes the result ambiguous unless one band is clearly longer (the nearer, larger roped
   trunk). ``pick_xy`` selects the nearest candidate instead.
6. The chosen band is refined at full resolution in a small window (mask, centre line,
   thickness as the full width at half maximum of the red-ness profile across the band); a band
   that turns out blob-like there is dropped and the next one taken.

Measured on 186 synthetic 1280x960 photos and 24 real rope-free photos: see
``python -m monodbh.toolkit.bench_rope --help``. Ropes whose red-ness contrast to the bark is
below ~0.02 (thin ropes far away in haze) are mostly missed; flagging tape that is not orange
looks like a rope here and is left to the pipeline's ``height_check``.

Examples
--------
>>> det = detect_rope(rgb)                          # doctest: +SKIP
>>> if det:                                         # doctest: +SKIP
...     print(det.center_xy, det.thickness_px)
... else:
...     print(det.reason)
"""
from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np

__all__ = ["RopeDetection", "RopeCandidate", "detect_rope", "redness_map", "red_shift_map", "line_contrast", "rope_profile_fwhm", "SCORE_WEIGHTS"]


@dataclass
class RopeCandidate:
    """One scored rope hypothesis (full-resolution pixel coordinates once returned).

    Attributes
    ----------
    center_xy : (x, y) middle of the band.
    direction : unit (dx, dy) of the band at its middle, dx >= 0.
    length_px, thickness_px : band extent along and across.
    score : higher is more rope-like (comparable between candidates of one photo).
    contrast : mean red-ness contrast of the band.
    coverage : fraction of the band's length where it is seen (gaps = occluders).
    span : fraction of the trunk width the band spans (NaN without a tree mask).
    hue : mean orange-ness ``(G - B) / R`` of the band.
    polyline : (N, 2) float32 centre line (x, y).
    features : the values entering the score (see :func:`candidate_features`).
    """
    center_xy: tuple[float, float]
    direction: tuple[float, float]
    length_px: float
    thickness_px: float
    score: float = 0.0
    contrast: float = 0.0
    coverage: float = 1.0
    span: float = float("nan")
    hue: float = 0.0
    polyline: np.ndarray | None = field(default=None, repr=False)
    features: dict = field(default_factory=dict, repr=False)
    level: int = field(default=0, repr=False)
    resid: float = field(default=0.0, repr=False)
    members: int = field(default=1, repr=False)
    clutter: float = field(default=0.0, repr=False)
    density: float = field(default=0.0, repr=False)
    edges: tuple = field(default=(0.0, 0.0), repr=False)
    step: float = field(default=0.0, repr=False)
    red: float = field(default=0.0, repr=False)
    red_area: float = field(default=0.0, repr=False)
    peaky: float = field(default=0.0, repr=False)
    edge_snr: float = field(default=0.0, repr=False)
    corr: float = field(default=0.0, repr=False)
    deep: bool = field(default=False, repr=False)

    def as_dict(self) -> dict:
        """JSON-friendly summary."""
        return dict(center_xy=[round(float(v), 1) for v in self.center_xy],
                    direction=[round(float(v), 4) for v in self.direction],
                    length_px=round(float(self.length_px), 1), thickness_px=round(float(self.thickness_px), 2),
                    score=round(float(self.score), 4))


@dataclass
class RopeDetection:
    """Result of :func:`detect_rope`; falsy when no (unambiguous) rope was found.

    Attributes
    ----------
    found : a single rope was found.
    reason : why not found, or the ambiguity message naming the candidate positions; ``""`` if found.
    center_xy : (x, y) where the rope crosses the middle of the trunk, full-resolution pixels.
    direction : unit (dx, dy) of the band across the trunk (dx >= 0).
    polyline : (N, 2) float32 rope centre line (x, y) pixels.
    thickness_px : rope thickness across the band, pixels.
    mask : (H, W) bool rope pixels (None when not found).
    score : score of the chosen candidate (0 when none).
    candidates : scored alternatives, best first (for ``--pick`` and error messages).
    ambiguous : two candidates scored within the ambiguity margin (then ``found`` is False).
    weak : found only below ``min_score`` (above ``weak_score``): to be confirmed by the caller.
    timings_ms : time per stage.
    """
    found: bool
    reason: str = ""
    center_xy: tuple[float, float] | None = None
    direction: tuple[float, float] | None = None
    polyline: np.ndarray | None = field(default=None, repr=False)
    thickness_px: float = float("nan")
    mask: np.ndarray | None = field(default=None, repr=False)
    score: float = 0.0
    candidates: list[RopeCandidate] = field(default_factory=list, repr=False)
    ambiguous: bool = False
    timings_ms: dict = field(default_factory=dict, repr=False)
    weak: bool = False

    def __bool__(self) -> bool:
        return bool(self.found)


# ----------------------------------------------------------------------------- low-level maps

def red_shift_map(rgb: np.ndarray, offset: float = 30.0) -> np.ndarray:
    """Unclipped red chromaticity ``(R - max(G, B) - max(G - B, 0) / 2) / (R + G + B + offset)``.

    Negative on green, grey and blue pixels, so a rope thinner than a pixel still raises the
    mean of its row on a greenish or hazy trunk, where :func:`redness_map` (this map clipped at
    0) is 0 on the rope and on the bark alike (the stem search of ``rope_stem`` for the rope
    verifier).

    Parameters
    ----------
    rgb : (H, W, 3) uint8 RGB.
    offset : damps the noisy chromaticity of dark pixels.

    Returns
    -------
    (H, W) float32 in (-1, 1).

    Examples
    --------
    >>> px = np.array([[[111, 127, 113], [105, 106, 95]]], np.uint8)   # bark, rope row
    >>> m = red_shift_map(px)
    >>> bool(m[0, 1] > m[0, 0]), float(redness_map(px).max())
    (True, 0.0)
    """
    R, G, B = cv2.split(rgb)
    # (in place where possible: a fresh 8 MB array per step costs its page faults, 1600 px photo)
    num = cv2.subtract(R, cv2.max(G, B), dtype=cv2.CV_32F)              # signed
    cv2.addWeighted(num, 1.0, cv2.subtract(G, B), -0.5, 0.0, dst=num, dtype=cv2.CV_32F)   # G - B saturates at 0
    den = cv2.addWeighted(R, 1.0, G, 1.0, float(offset), dtype=cv2.CV_32F)
    cv2.add(den, B, dst=den, dtype=cv2.CV_32F)
    return cv2.divide(num, den, dst=num)


def redness_map(rgb: np.ndarray, offset: float = 30.0) -> np.ndarray:
    """Red chromaticity ``max(0, R - max(G, B) - max(G - B, 0) / 2) / (R + G + B + offset)``.

    :func:`red_shift_map` clipped at 0, so that a grey band between green leaves is no "redder"
    than its neighbours.

    Parameters
    ----------
    rgb : (H, W, 3) uint8 RGB.
    offset : damps the noisy chromaticity of dark pixels.

    Returns
    -------
    (H, W) float32 in [0, 1).
    """
    m = red_shift_map(rgb, offset)
    return np.maximum(m, 0.0, out=m)


def line_contrast(F: np.ndarray, ds: tuple[int, ...] = (2, 3), sigma_x: float = 2.0,
                  sigma_y: float = 0.7) -> np.ndarray:
    """Contrast of thin, horizontal-ish bright lines in ``F``.

    ``max_d min(G(y) - G(y - d), G(y) - G(y + d))`` with ``G`` = ``F`` blurred anisotropically
    (``sigma_x`` along the line, ``sigma_y`` across), clipped at 0.

    Parameters
    ----------
    F : (H, W) float32.
    ds : vertical offsets in pixels (about the half-thickness plus one).

    Returns
    -------
    (H, W) float32 >= 0, in the units of ``F``.
    """
    G = cv2.GaussianBlur(F, (0, 0), sigmaX=sigma_x, sigmaY=sigma_y)
    H = G.shape[0]
    out = np.zeros_like(G)
    abuf, bbuf = np.empty_like(G), np.empty_like(G)      # (reused: no fresh pages per step)
    for d in ds:
        if 2 * d >= H:
            continue
        n = H - 2 * d
        a = cv2.subtract(G[d:H - d], G[:n], dst=abuf[:n])
        b = cv2.subtract(G[d:H - d], G[2 * d:], dst=bbuf[:n])
        cv2.min(a, b, dst=a)
        o = out[d:H - d]
        cv2.max(o, a, dst=o)
    return out


# ----------------------------------------------------------------------------- pieces

_SEG_KEYS = ("cx", "cy", "theta", "length", "thick", "contrast", "hue", "red", "area", "level")


def _segments(R: np.ndarray, F: np.ndarray, rgb: np.ndarray, thr: float, min_len: float, level: int):
    """Components of ``R > thr`` described by moments, in level-0 pixels.

    Returns a dict of (K,) arrays (see ``_SEG_KEYS``) or None.
    """
    f = 2.0 ** level
    m = cv2.compare(R, thr, cv2.CMP_GT)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    if n <= 1:
        return None
    w = stats[1:, cv2.CC_STAT_WIDTH]
    h = stats[1:, cv2.CC_STAT_HEIGHT]
    keep = np.flatnonzero((w + h >= min_len) & (w >= 0.6 * h)) + 1
    if len(keep) == 0:
        return None
    remap = np.zeros(n, np.int32)
    remap[keep] = np.arange(1, len(keep) + 1)
    ys, xs = np.nonzero(m)                     # sparse: only line pixels
    li = remap[lab[ys, xs]]
    sel = li > 0
    ys, xs, li = ys[sel], xs[sel], li[sel] - 1
    k = len(keep)
    wts = R[ys, xs].astype(np.float64)
    cnt = np.bincount(li, minlength=k).astype(np.float64)
    cx = np.bincount(li, xs, k) / cnt
    cy = np.bincount(li, ys, k) / cnt
    dx = xs - cx[li]
    dy = ys - cy[li]
    cxx = np.bincount(li, dx * dx, k) / cnt
    cyy = np.bincount(li, dy * dy, k) / cnt
    cxy = np.bincount(li, dx * dy, k) / cnt
    theta = 0.5 * np.arctan2(2 * cxy, cxx - cyy)           # major axis angle (image coords)
    u = dx * np.cos(theta)[li] + dy * np.sin(theta)[li]
    umin = np.full(k, np.inf)
    umax = np.full(k, -np.inf)
    np.minimum.at(umin, li, u)
    np.maximum.at(umax, li, u)
    length = umax - umin + 1.0
    thick = cnt / length
    ang = np.abs(((theta + np.pi / 2) % np.pi) - np.pi / 2)      # 0 = horizontal
    ok = (ang < np.deg2rad(55)) & (length >= min_len) & (length >= 1.5 * thick)
    if not ok.any():
        return None
    px = rgb[ys, xs].astype(np.float32)
    hue = (px[:, 1] - px[:, 2]) / (px[:, 0] + 8.0)      # orange-ness (G - B) / R, weighted by contrast
    sw = np.bincount(li, wts, k)
    seg = dict(cx=cx * f, cy=cy * f, theta=theta, length=length * f,
               thick=thick * f, contrast=sw / cnt, hue=np.bincount(li, hue * wts ** 3, k) / np.bincount(li, wts ** 3, k),
               red=np.bincount(li, F[ys, xs] * wts, k) / sw,
               area=cnt * f * f, level=np.full(k, level))
    return {kk: v[ok] for kk, v in seg.items()}


def _link(seg: dict) -> list[list[int]]:
    """Chains of segments linked end to end (a band broken by occluders, a knot or noise)."""
    n = len(seg["cx"])
    if n == 0:
        return []
    cx, cy, th, L, T = seg["cx"], seg["cy"], seg["theta"], seg["length"], seg["thick"]
    ct, st = np.cos(th), np.sin(th)
    sgn = np.where(ct < 0, -1.0, 1.0)
    ux, uy = ct * sgn, st * sgn
    xl, yl = cx - 0.5 * L * ux, cy - 0.5 * L * uy
    xr, yr = cx + 0.5 * L * ux, cy + 0.5 * L * uy
    slope = uy / np.maximum(ux, 0.3)
    nxt = -np.ones(n, int)
    prv = -np.ones(n, int)
    if n > 1:
        gap = xl[None, :] - xr[:, None]                        # i's right end -> j's left end
        pred_j = yr[:, None] + slope[:, None] * gap
        pred_i = yl[None, :] - slope[None, :] * gap
        err = np.minimum(np.abs(pred_j - yl[None, :]), np.abs(pred_i - yr[:, None]))
        tmax = np.maximum(T[:, None], T[None, :])
        tmin = np.minimum(T[:, None], T[None, :])
        lsum = L[:, None] + L[None, :]
        lmin = np.minimum(L[:, None], L[None, :])
        gpos = np.maximum(gap, 0.0)
        tol = 1.0 + 0.6 * tmax + 0.1 * gpos
        dth = np.abs(np.arctan(slope[:, None]) - np.arctan(slope[None, :]))
        ok = ((gap > -0.3 * lmin - 2) & (gap < 0.8 * lsum + 4) & (err < tol) & (tmax < 2.5 * tmin + 1.5)
              & (dth < np.deg2rad(40)) & (np.abs(seg["hue"][:, None] - seg["hue"][None, :]) < 0.15)
              & (seg["level"][:, None] == seg["level"][None, :]))
        np.fill_diagonal(ok, False)
        ii, jj = np.nonzero(ok)
        if len(ii):
            cost = err[ii, jj] / tol[ii, jj] + gpos[ii, jj] / lsum[ii, jj]
            for q in np.argsort(cost):
                i, j = ii[q], jj[q]
                if nxt[i] < 0 and prv[j] < 0:
                    # no cycles: walk back from i
                    k, cyc = i, False
                    while k >= 0:
                        if k == j:
                            cyc = True
                            break
                        k = prv[k]
                    if not cyc:
                        nxt[i] = j
                        prv[j] = i
    chains = []
    for s in np.flatnonzero(prv < 0):
        ch = [int(s)]
        while nxt[ch[-1]] >= 0:
            ch.append(int(nxt[ch[-1]]))
        chains.append(ch)
    seg["xl"], seg["yl"], seg["xr"], seg["yr"] = xl, yl, xr, yr
    return chains


def _runs(seg: dict, chains: list[list[int]], min_contrast: float, max_run: int = 8) -> list[list[int]]:
    """Runs of up to ``max_run`` consecutive linked pieces worth fitting, best band score first.

    Per chain: its 3 best runs and its 3 best single pieces (a sub-run may be the rope and the
    whole chain the rope plus collinear clutter, or the reverse).
    """
    out, scores = [], []
    single = np.array([len(ch) == 1 for ch in chains], bool)
    if single.any():                                   # vectorised: most chains are one piece
        q = np.array([ch[0] for ch, s1 in zip(chains, single) if s1])
        s = _band_score(seg["contrast"][q], seg["length"][q], seg["thick"][q], 1.0, seg["hue"][q])
        s[(seg["contrast"][q] < min_contrast) | (seg["length"][q] < 8)] = 0.0
        for k in np.flatnonzero(s > 0):
            out.append([int(q[k])])
            scores.append(s[k])
    for ch in (ch for ch, s1 in zip(chains, single) if not s1):
        ch = np.asarray(ch)
        n = len(ch)
        a = seg["area"][ch]
        A = np.concatenate([[0.0], np.cumsum(a)])
        CL = np.concatenate([[0.0], np.cumsum(seg["length"][ch])])
        AC = np.concatenate([[0.0], np.cumsum(a * seg["contrast"][ch])])
        AH = np.concatenate([[0.0], np.cumsum(a * seg["hue"][ch])])
        i, j = np.meshgrid(np.arange(n), np.arange(1, n + 1), indexing="ij")
        ok = (j > i) & (j - i <= max_run)
        i, j = i[ok], j[ok]
        area = A[j] - A[i]
        covered = CL[j] - CL[i]
        con = (AC[j] - AC[i]) / area
        hue = (AH[j] - AH[i]) / area
        ext = np.hypot(seg["xr"][ch][j - 1] - seg["xl"][ch][i], seg["yr"][ch][j - 1] - seg["yl"][ch][i]) + 1.0
        ext = np.maximum(ext, seg["length"][ch][i])
        s = _band_score(con, ext, area / np.maximum(covered, 1.0), np.minimum(1.0, covered / ext), hue)
        s[(con < min_contrast) | (ext < 8)] = 0.0
        sel = list(np.argsort(-s)[:3])
        one = np.flatnonzero(j - i == 1)
        sel += list(one[np.argsort(-s[one])[:3]])
        for q in dict.fromkeys(sel):
            if s[q] > 0:
                out.append([int(v) for v in ch[i[q]:j[q]]])
                scores.append(s[q])
    order = np.argsort(-np.asarray(scores)) if scores else []
    return [out[q] for q in order]


def _diverse(seg: dict, runs: list[list[int]], n: int, cell: float, extra: int, per_cell: int = 2) -> list[list[int]]:
    """The runs to score fully: the ``n`` best by band score, plus up to ``extra`` of the rest
    from ``cell`` x ``cell`` squares (working pixels, by the run's centre) that none of those
    ``n`` occupies, at most ``per_cell`` per square.

    A patch of red clutter (fallen leaves, a jacket, berries) yields dozens of short bands that
    outrank a faint rope by the band score alone and would otherwise take the whole budget.
    """
    if len(runs) <= n:
        return runs
    cx, cy, a = seg["cx"], seg["cy"], seg["area"]

    def key(r):
        return (int(np.average(cx[r], weights=a[r]) // cell), int(np.average(cy[r], weights=a[r]) // cell))

    out = list(runs[:n])
    taken = {key(r) for r in out}
    used: dict = {}
    for r in runs[n:]:
        if len(out) >= n + extra:
            break
        k = key(r)
        if k in taken or used.get(k, 0) >= per_cell:
            continue
        used[k] = used.get(k, 0) + 1
        out.append(r)
    return out


def _band_score(contrast, length, thick, coverage, hue):
    """Cheap ranking score from the band alone (contrast, length, continuity, thinness, hue)."""
    T = np.maximum(thick, 0.7)
    shape = np.clip((length / T - 3.0) / 10.0, 0.0, 1.0)
    hue_pen = np.clip(1.0 - 3.0 * np.maximum(0.0, hue - 0.2), 0.25, 1.0)
    return contrast * np.sqrt(length) * (0.3 + 0.7 * coverage) * shape * hue_pen


def _make_candidate(seg: dict, idx: list[int]) -> RopeCandidate:
    """Fit a band (quadratic centre line) through member pieces ``idx`` (level-0 pixels)."""
    idx = np.asarray(idx)
    xl, yl, xr, yr = seg["xl"][idx], seg["yl"][idx], seg["xr"][idx], seg["yr"][idx]
    cx, cy = seg["cx"][idx], seg["cy"][idx]
    a = seg["area"][idx]
    x0, x1 = float(xl.min()), float(xr.max())
    if len(idx) == 1:
        coef = np.array([cy[0], (yr[0] - yl[0]) / max(xr[0] - xl[0], 1e-3), 0.0])
        xm = float(cx[0])
        resid = 0.0
    else:
        px = np.concatenate([xl, cx, xr])
        py = np.concatenate([yl, cy, yr])
        pw = np.tile(a * seg["contrast"][idx], 3) * np.repeat([1.0, 2.0, 1.0], len(idx))
        xm = float(np.average(px, weights=pw))
        A = np.stack([np.ones_like(px), px - xm, (px - xm) ** 2], 1)
        sw = np.sqrt(pw)
        coef = np.linalg.lstsq(A * sw[:, None], py * sw, rcond=None)[0]
        resid = float(np.sqrt(np.average((py - A @ coef) ** 2, weights=pw)))
    xs = np.linspace(x0, x1, 24)
    ys = coef[0] + coef[1] * (xs - xm) + coef[2] * (xs - xm) ** 2
    arc = float(np.hypot(np.diff(xs), np.diff(ys)).sum()) + 1.0
    covered = float(np.sum(seg["length"][idx]))
    area = float(a.sum())
    xc = 0.5 * (x0 + x1)
    yc = coef[0] + coef[1] * (xc - xm) + coef[2] * (xc - xm) ** 2
    d = np.array([1.0, coef[1] + 2 * coef[2] * (xc - xm)])
    d /= np.linalg.norm(d)
    return RopeCandidate(
        center_xy=(float(xc), float(yc)), direction=(float(d[0]), float(d[1])),
        length_px=arc, thickness_px=area / max(covered, 1.0),
        contrast=float(np.average(seg["contrast"][idx], weights=a)), coverage=min(1.0, covered / arc),
        hue=float(np.average(seg["hue"][idx], weights=a)), red=float(np.average(seg["red"][idx], weights=a)),
        polyline=np.stack([xs, ys], 1).astype(np.float32),
        level=int(np.round(np.average(seg["level"][idx], weights=a))), resid=resid, members=len(idx))


# ----------------------------------------------------------------------------- context

class _Counts:
    """Box counts of a binary map on a grid of ``cell`` x ``cell`` pixels (integral image)."""

    def __init__(self, mask: np.ndarray, cell: int = 4):
        h, w = mask.shape
        hc, wc = -(-h // cell), -(-w // cell)
        # the pixel-level integral image sampled at the cell corners (the cell grid's integral:
        # the same integer counts as summing each cell first, 4x faster at 1600 px)
        m = np.asarray(mask)
        m = m.view(np.uint8) if m.dtype == bool else (m != 0).astype(np.uint8)
        full = cv2.integral(np.ascontiguousarray(m), sdepth=cv2.CV_32S)
        ys = np.minimum(np.arange(hc + 1) * cell, h)
        xs = np.minimum(np.arange(wc + 1) * cell, w)
        self.I = full[ys][:, xs].astype(np.float64)
        self.cell, self.hc, self.wc = cell, hc, wc

    def _cells(self, x0, y0, x1, y1):
        c = self.cell
        return (min(max(round(x0 / c), 0), self.wc), min(max(round(y0 / c), 0), self.hc),
                min(max(round(x1 / c), 0), self.wc), min(max(round(y1 / c), 0), self.hc))

    def __call__(self, x0, y0, x1, y1) -> float:
        """Count of set pixels in the box [x0, x1) x [y0, y1) (rounded to cells)."""
        a, u, b, v = self._cells(x0, y0, x1, y1)
        if b <= a or v <= u:
            return 0.0
        I = self.I
        return float(I[v, b] - I[u, b] - I[v, a] + I[u, a])

    def area(self, x0, y0, x1, y1) -> float:
        """Pixel area of the same (rounded) box."""
        a, u, b, v = self._cells(x0, y0, x1, y1)
        return float(max(0, b - a) * max(0, v - u) * self.cell ** 2)


def _clutter(c: RopeCandidate, counts: _Counts) -> None:
    """Thin red lines around a candidate (level-0 pixels).

    ``clutter``: line pixels on the trunk face just above and below the band (within its x range),
    relative to the band's area; ``density``: fraction of line pixels in a box around the band.
    """
    p, L, T = c.polyline, c.length_px, max(c.thickness_px, 1.0)
    x0, x1 = p[0, 0] + 0.1 * L, p[-1, 0] - 0.1 * L
    ya, yb = p[:, 1].min(), p[:, 1].max()
    face = counts(x0, ya - 0.5 * L, x1, yb + 0.5 * L)
    band = counts(x0, ya - T - 2, x1, yb + T + 2)
    c.clutter = max(0.0, face - band) / max(L * T, 1.0)
    m = max(16.0, 0.6 * L)
    box = (p[0, 0] - m, ya - m, p[-1, 0] + m, yb + m)
    c.density = counts(*box) / max(counts.area(*box), 1.0)


def _maxfilt(v: np.ndarray, r: int) -> np.ndarray:
    """Running maximum along the rows of a (K, N) float32 array over windows of half width ``r``."""
    if r <= 0:
        return v
    return cv2.dilate(v, _line_kernel(r), borderType=cv2.BORDER_REPLICATE)


@functools.lru_cache(maxsize=256)
def _line_kernel(r: int) -> np.ndarray:
    return np.ones((1, 2 * r + 1), np.uint8)


def _edges(c: RopeCandidate, gray_integral: np.ndarray) -> None:
    """Do both band ends sit on a vertical intensity edge (the trunk silhouette)?

    For each end, the grey column means of horizontal strips (``_EDGE_NSTRIP`` above and below
    the band, each ``_EDGE_STRIP`` times the band length high) are
    taken in a window around the end; a step between the means of two adjacent boxes must appear
    in every strip with the same sign, allowing for a trunk leaning up to 15 deg.
    ``edges`` = per end ``step / (step + 6)`` (grey levels); ``edge_snr`` = geometric mean over
    the ends of the step over the median step in the window (a lone silhouette vs foliage texture).
    """
    II = gray_integral
    H, W = II.shape[0] - 1, II.shape[1] - 1
    L = c.length_px
    T = max(c.thickness_px, 1.0)
    p = c.polyline
    hs = int(min(max(_EDGE_STRIP * L, 4), 160))        # height of each sub-strip
    a = int(min(max(0.05 * L, 1), 16))                 # width of the step boxes
    s = int(min(max(0.2 * L, 3), 100))                 # search range around the band end
    out, snr = [], []
    for (xe, ye) in (p[0], p[-1]):
        xa = int(round(xe)) - s - a - 1
        xb = int(round(xe)) + s + a + 2
        prof, reach = [], []
        if xa >= 0 and xb <= W:
            for k in range(-_EDGE_NSTRIP, _EDGE_NSTRIP):
                # strips above (k < 0) and below (k >= 0) the band; dist = strip centre to band
                ya = ye - T - 1 + k * hs if k < 0 else ye + T + 1 + k * hs
                dist = (abs(k + 0.5) if k >= 0 else abs(k) - 0.5) * hs
                ya = int(round(ya))
                if ya < 0 or ya + hs > H:
                    continue
                # running sum over x of the strip's column sums, divided by the strip height
                prof.append((II[ya + hs, xa:xb + 1] - II[ya, xa:xb + 1]) / hs)
                reach.append(int(round(0.27 * (dist + T))))
        if len(prof) < 2:
            out.append(0.0)
            snr.append(0.0)
            continue
        P = np.stack(prof).astype(np.float32)
        D = (P[:, 2 * a:] - 2 * P[:, a:-a] + P[:, :-2 * a]) / a    # right box mean - left box mean
        if D.shape[1] == 0:
            out.append(0.0)
            snr.append(0.0)
            continue
        # both step signs at once; strips with the same lean allowance dilated together
        DD = np.concatenate([D, -D])
        rr = np.array(reach + reach)
        M = np.empty_like(DD)
        for r in np.unique(rr):
            M[rr == r] = _maxfilt(DD[rr == r], int(r))
        n = len(D)
        best = max(0.0, float(M[:n].min(0).max()), float(M[n:].min(0).max()))
        out.append(best / (best + 6.0))
        snr.append(best / (float(np.median(np.abs(D))) + 2.0))
    c.edges = (out[0], out[1])
    c.edge_snr = float(np.sqrt(snr[0] * snr[1])) if len(snr) == 2 else 0.0


def _continuity(c: RopeCandidate, iis: list[np.ndarray]) -> None:
    """Is the surface just above the band the same as just below it (one trunk face)?

    Mean column profiles (grey, and red minus blue) of a strip above and a strip below the band,
    within its x range, are compared. A rope on a trunk has the same bark, lit the same way
    (similar means, correlated profiles); a horizon or a ground edge running between two trunks
    has sky or far trees above and ground below. ``step``: largest relative difference of means;
    ``corr``: correlation of the grey profiles (0 when too few columns).
    """
    L = c.length_px
    T = max(c.thickness_px, 1.0)
    p = c.polyline
    H, W = iis[0].shape[0] - 1, iis[0].shape[1] - 1
    x0 = int(round(p[0, 0] + 0.15 * L))
    x1 = int(round(p[-1, 0] - 0.15 * L))
    hs = int(min(max(0.25 * L, 3), 60))
    inner = p[(p[:, 0] >= x0) & (p[:, 0] <= x1), 1]
    if x1 - x0 < 3 or len(inner) == 0:
        c.step, c.corr = 0.5, 0.0
        return
    ya1 = int(round(inner.min() - T - 1))
    yb0 = int(round(inner.max() + T + 1))
    ya0, yb1 = ya1 - hs, yb0 + hs
    if ya0 < 0 or yb1 > H or x0 < 0 or x1 >= W:
        c.step, c.corr = 0.5, 0.0
        return
    steps, prof = [], []
    for k, II in enumerate(iis):
        a = np.diff(II[ya1, x0:x1 + 2] - II[ya0, x0:x1 + 2]) / hs
        b = np.diff(II[yb1, x0:x1 + 2] - II[yb0, x0:x1 + 2]) / hs
        ma, mb = float(a.mean()), float(b.mean())
        steps.append(abs(ma - mb) / (20.0 + (0.5 * (abs(ma) + abs(mb)) if k == 0 else 0.0)))
        if k == 0:
            prof = (a, b)
    c.step = float(max(steps))
    a, b = prof
    sa, sb = a.std(), b.std()
    c.corr = float(np.mean((a - a.mean()) * (b - b.mean())) / (sa * sb)) if sa > 1.0 and sb > 1.0 else 0.0


def _red_area(c: RopeCandidate, F: np.ndarray) -> None:
    """Fraction of the surroundings (band excluded) about as red as the band: red leaves, a jacket
    or a blob light up around a "band" found inside them; bark around a rope does not."""
    H, W = F.shape
    p, L, T = c.polyline, c.length_px, max(c.thickness_px, 1.0)
    x0, x1 = int(max(0, p[0, 0] - 0.3 * L)), int(min(W, p[-1, 0] + 0.3 * L + 1))
    y0, y1 = int(max(0, p[:, 1].min() - 0.5 * L)), int(min(H, p[:, 1].max() + 0.5 * L + 1))
    st = max(1, int(L / 40))
    sub = F[y0:y1:st, x0:x1:st]
    if sub.size == 0:
        c.red_area = 0.0
        return
    xs = np.arange(x0, x1, st)
    yc = np.interp(xs, p[:, 0], p[:, 1])
    band = np.abs(np.arange(y0, y1, st)[:, None] - yc[None, :]) <= T + 2
    v = sub[~band]
    c.red_area = float(np.mean(v > 0.5 * c.red)) if v.size else 0.0


def _uniformity(c: RopeCandidate, Rs: list[np.ndarray]) -> None:
    """How even the line contrast is along the band: ``peaky`` = log(90th percentile / median)
    of the per-column maxima. A rope is even; a row of red dots (leaves, berries) is peaky."""
    lv = min(c.level, len(Rs) - 1)
    R = Rs[lv]
    f = 2.0 ** lv
    H, W = R.shape
    p = c.polyline / f
    xs = np.arange(int(np.ceil(p[0, 0])), int(np.floor(p[-1, 0])) + 1)
    xs = xs[(xs >= 0) & (xs < W)]
    if len(xs) < 3:
        c.peaky = 0.0
        return
    yc = np.interp(xs, p[:, 0], p[:, 1])
    r = int(np.ceil(0.5 * c.thickness_px / f)) + 1
    rows = np.clip(np.round(yc)[None, :].astype(int) + np.arange(-r, r + 1)[:, None], 0, H - 1)
    v = R[rows, xs[None, :]].max(0)
    q50, q90 = np.percentile(v, [50, 90])
    c.peaky = float(np.log((q90 + 0.003) / (q50 + 0.003)))


#: Weights of the candidate score (log-odds): ``score = bias + sum_k w_k * feature_k``
#: (features: :func:`candidate_features`). Fitted with ``python -m monodbh.toolkit.bench_rope --fit
#: --extra-no-rope 36 --real-negatives /work/shared/data/real_trees`` (150 + 36 synthetic 1280x960
#: photos of seed 7000, and 24 rope-free real photos as negatives); the bias puts 10 % of the
#: rope-free photos (tape bands excluded) above 0.
SCORE_WEIGHTS = dict(bias=-1.085, log_contrast=1.956, log_length=0.456, log_density=-0.208, coverage=2.745,
                     shape=1.359, hue=-13.054, edge_min=1.022, edge_max=1.605, log_clutter=-0.774, members=-0.279,
                     coarse=-1.259, resid=-0.589, step=-2.38, corr=1.012, red_area=-2.366, peaky=-0.244,
                     log_red=0.419, log_edge_snr=1.163)


def candidate_features(c: RopeCandidate) -> dict:
    """Features of a candidate (working-image pixels) entering its score."""
    T = max(c.thickness_px, 0.7)
    return dict(
        log_contrast=float(np.log(min(c.contrast, 0.08))), log_length=float(np.log(c.length_px)),
        log_density=float(np.log(c.density + 0.002)), coverage=float(c.coverage),
        shape=float(np.clip((c.length_px / T - 3.0) / 10.0, 0.0, 1.0)), hue=float(max(0.0, c.hue - 0.15)),
        edge_min=float(min(c.edges)), edge_max=float(max(c.edges)), log_clutter=float(np.log1p(c.clutter)),
        members=float(c.members - 1), coarse=float(c.level == 2), resid=float(c.resid / T),
        step=float(min(c.step, 1.0)), corr=float(c.corr), red_area=float(c.red_area),
        peaky=float(c.peaky), log_red=float(np.log(c.red + 0.01)), log_edge_snr=float(np.log1p(c.edge_snr)))


def _score(c: RopeCandidate, weights: dict | None = None) -> float:
    """Log-odds that the candidate is the rope: ``bias + sum_k w_k * feature_k``."""
    w = SCORE_WEIGHTS if weights is None else weights
    c.features = candidate_features(c)
    if c.length_px < _MIN_ELONGATION * max(c.thickness_px, 0.7) or c.hue > _MAX_HUE:
        return -np.inf
    return float(w.get("bias", 0.0) + sum(w[k] * c.features[k] for k in c.features if k in w))


# ----------------------------------------------------------------------------- detector

_PIECE_THR = 0.012      # line-contrast level of the pixels forming pieces
_DEEP_PRIOR = 0.5       # log-odds taken off bands scored beyond the band-score budget (see _diverse)
_SIGMA_X = 2.0          # blur along the line before the contrast (pixels of each level)
_MAX_HUE = 0.35         # bands more orange than this ((G - B) / R) are tape, not rope
_MIN_ELONGATION = 5.0   # band length / thickness: a rope spans a trunk >= 5 tube diameters wide
_EDGE_STRIP = 0.2       # trunk-edge test: strip height relative to the band length ...
_EDGE_NSTRIP = 2        # ... and strips on each side of the band


def detect_rope(rgb: np.ndarray, tree_mask: np.ndarray | None = None, *,
                pick_xy: tuple[float, float] | None = None,
                height_check: Callable[[RopeCandidate], bool] | None = None,
                work_long_side: int = 1600, min_contrast: float = 0.015, min_score: float = 1.0,
                ambiguity_margin: float = 1.0, nearer_ratio: float = 1.6, max_candidates: int = 50,
                max_segments: int = 400, weights: dict | None = None,
                weak_score: float | None = None) -> RopeDetection:
    """Find the red rope tied around a trunk.

    Parameters
    ----------
    rgb : (H, W, 3) uint8 RGB photo.
    tree_mask : (H, W) bool trunk/tree pixels, optional; bands that lie on the mask and span the
        trunk's width there are preferred, bands off the mask are penalised.
    pick_xy : (x, y) full-resolution pixel: choose the candidate nearest to it (resolves ambiguity).
    height_check : optional callable ``candidate -> bool`` from the pipeline (e.g. "is this about
        1.3 m above the ground?"); candidates for which it returns False are dropped.
    work_long_side : candidates are searched on a copy downscaled to this long side.
    min_contrast : minimum mean red-ness contrast of a band.
    min_score : a candidate is a rope when its score (a log-odds) is above this. The score's bias
        puts 10 % of rope-free photos above 0; the default 1.0 trades recall for precision (a
        missed rope can be picked with ``pick_xy``, a false one would silently give a wrong DBH).
    ambiguity_margin : rope candidates on other bands scoring within this margin of the best
        (log-odds units) are rivals. Of the best and its rivals, one whose band is at least
        ``nearer_ratio`` times longer than each other's (a larger, nearer roped trunk) is taken;
        otherwise the result is ambiguous (``found=False``, ``ambiguous=True``) unless ``pick_xy``
        is given.
    nearer_ratio : see ``ambiguity_margin``.
    max_candidates : how many bands (by the cheap band score) get the full score; up to
        ``max_candidates // 2`` more from regions none of them occupies, scored ``_DEEP_PRIOR`` lower.
    max_segments : at most this many line pieces (the most contrasted) are linked into bands.
    weights : override :data:`SCORE_WEIGHTS`.
    weak_score : when no candidate scores above ``min_score``, the best one above
        ``weak_score`` is returned with ``weak=True`` (rivals judged among those), for the
        caller to verify with other evidence (the pipeline: does it lie across a segmented
        trunk?). ``None``: no weak results.

    Returns
    -------
    RopeDetection
        ``center_xy``/``polyline``/``mask`` in full-resolution pixels of ``rgb``.
    """
    t0 = time.perf_counter()
    tm: dict[str, float] = {}

    def lap(name):
        tm[name] = round(1000 * (time.perf_counter() - t0) - sum(tm.values()), 2)

    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    H, W = rgb.shape[:2]
    if tree_mask is not None:
        tree_mask = np.asarray(tree_mask, bool)
        if tree_mask.shape != (H, W):
            raise ValueError(f"tree_mask shape {tree_mask.shape} != image {(H, W)}")
    small = _downscale(rgb, work_long_side)
    sx, sy = W / small.shape[1], H / small.shape[0]
    lap("resize")

    thr = _PIECE_THR
    segs, img, counts, Rs = [], small, None, []
    for level in range(3):
        F = redness_map(img)
        R = line_contrast(F, sigma_x=_SIGMA_X)
        Rs.append(R)
        if level == 0:
            counts = _Counts(R > thr)
            F0 = F
        sg = _segments(R, F, img, thr=thr, min_len=5.0, level=level)
        if sg is not None:
            segs.append(sg)
        if level < 2 and min(img.shape[:2]) >= 64:
            img = cv2.pyrDown(img)
        else:
            break
    lap("lines")
    none = RopeDetection(False, "no red rope found (no thin red band across a trunk)", timings_ms=tm)
    if not segs:
        return none
    seg = {k: np.concatenate([g[k] for g in segs]) for k in _SEG_KEYS}
    keep = (seg["contrast"] >= min_contrast) | (seg["length"] >= 10)
    seg = {k: v[keep] for k, v in seg.items()}
    if len(seg["cx"]) > max_segments:
        top = np.argsort(-seg["contrast"] * np.sqrt(seg["length"]))[:max_segments]
        seg = {k: v[top] for k, v in seg.items()}
    runs = _diverse(seg, _runs(seg, _link(seg), min_contrast), max_candidates,
                    cell=max(32.0, max(small.shape[:2]) / 16.0), extra=max_candidates // 2)
    cands = [_make_candidate(seg, idx) for idx in runs]
    for c in cands[max_candidates:]:
        c.deep = True
    lap("bands")
    gray_ii = cv2.integral(cv2.cvtColor(small, cv2.COLOR_RGB2GRAY), sdepth=cv2.CV_32S)
    rb = cv2.addWeighted(small[..., 0], 0.5, small[..., 2], -0.5, 128.0)       # (R - B) / 2 + 128, uint8
    rb_ii = cv2.integral(rb, sdepth=cv2.CV_32S)
    for c in cands:
        _clutter(c, counts)
        _edges(c, gray_ii)
        _continuity(c, [gray_ii, rb_ii])
        _red_area(c, F0)
        _uniformity(c, Rs)
        c.score = _score(c, weights) - (_DEEP_PRIOR if c.deep else 0.0)
    # to full-resolution pixels
    for c in cands:
        c.polyline = (c.polyline + 0.5) * np.array([sx, sy], np.float32) - 0.5
        c.center_xy = ((c.center_xy[0] + 0.5) * sx - 0.5, (c.center_xy[1] + 0.5) * sy - 0.5)
        c.length_px *= sx
        c.thickness_px *= sy
    if tree_mask is not None:
        for c in cands:
            _apply_tree_mask(c, tree_mask)
    if height_check is not None:
        cands = [c for c in cands if height_check(c)]
    cands = [c for c in cands if np.isfinite(c.score)]
    cands.sort(key=lambda c: -c.score)
    cands = _dedupe(cands)
    lap("score")
    # choose; a chosen band whose full-resolution refinement is not band-like (a blob) is dropped
    for _ in range(3):
        best = _choose(cands, pick_xy, min_score, ambiguity_margin, nearer_ratio)
        if best is None and weak_score is not None and pick_xy is None:
            best = _choose(cands, None, weak_score, ambiguity_margin, nearer_ratio)
        if best is None or isinstance(best, str):
            break
        det = _refine(rgb, best, tree_mask)
        arc = float(np.hypot(*np.diff(det.polyline, axis=0).T).sum()) + 1.0
        if arc >= _MIN_ELONGATION * max(det.thickness_px, 0.7):
            det.candidates = cands
            det.weak = pick_xy is None and not best.score > min_score
            lap("refine")
            tm["total"] = round(1000 * (time.perf_counter() - t0), 2)
            det.timings_ms = tm
            return det
        best.score = -np.inf
        cands = [c for c in cands if c is not best]
    if isinstance(best, str):
        return RopeDetection(False, best, candidates=cands, ambiguous=True, timings_ms=tm)
    none.candidates = cands
    return none


def _choose(cands: list[RopeCandidate], pick_xy, min_score: float, ambiguity_margin: float,
            nearer_ratio: float) -> RopeCandidate | str | None:
    """The candidate to report, an ambiguity message, or None (see :func:`detect_rope`)."""
    if pick_xy is not None:
        if not cands:
            return None
        px, py = pick_xy
        near = [c for c in cands[:30] if c.score > min_score - 3.0] or cands[:30]
        return min(near, key=lambda c: _dist_to(c, px, py))
    ropes = [c for c in cands if c.score > min_score]
    if not ropes:
        return None
    best = ropes[0]
    rivals = [c for c in ropes[1:] if c.score >= best.score - ambiguity_margin]
    if not rivals:
        return best
    if all(_overlapping(best, c) for c in rivals):
        # the same rope found more than once (pyramid levels, pieces): the longest band
        return max([best] + rivals, key=lambda c: c.length_px)
    group = [best] + rivals
    longest = max(group, key=lambda c: c.length_px)
    if all(longest.length_px >= nearer_ratio * c.length_px for c in group if c is not longest):
        return longest
    c1, c2 = group[0], group[1]
    return (f"two rope candidates at ({c1.center_xy[0]:.0f},{c1.center_xy[1]:.0f}) and "
            f"({c2.center_xy[0]:.0f},{c2.center_xy[1]:.0f}) (e.g. two roped trees); choose one with --pick X,Y")


def _overlapping(a: RopeCandidate, b: RopeCandidate) -> bool:
    """Whether two bands lie on one line and overlap along it (the same rope found twice, e.g.
    at two pyramid levels or in two pieces): not rivals. Ropes on two trunks cannot overlap."""
    u = np.asarray(a.direction, np.float64)
    u = u / max(np.linalg.norm(u), 1e-9)
    v = np.asarray(b.direction, np.float64)
    v = v / max(np.linalg.norm(v), 1e-9)
    if abs(u @ v) < np.cos(np.radians(15)):
        return False
    d = np.asarray(b.center_xy, np.float64) - np.asarray(a.center_xy, np.float64)
    perp = abs(d[0] * u[1] - d[1] * u[0])
    along = abs(d @ u)
    return perp <= max(3.0, 2.0 * (a.thickness_px + b.thickness_px)) and along < 0.5 * (a.length_px + b.length_px)


def _downscale(rgb: np.ndarray, long_side: int) -> np.ndarray:
    """Shrink so that the long side is at most ``long_side``.

    Exact 2x area halvings (fast) while the image is at least twice too large, then one linear
    step by a factor below 2 (a line 1 px wide after it still spans >= 1 sample).
    """
    img = rgb
    while max(img.shape[:2]) >= 2 * long_side:
        img = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)
    H, W = img.shape[:2]
    if max(H, W) > long_side:
        s = long_side / max(H, W)
        img = cv2.resize(img, (round(W * s), round(H * s)), interpolation=cv2.INTER_LINEAR)
    return img


def _dist_to(c: RopeCandidate, px: float, py: float) -> float:
    return float(np.min(np.hypot(c.polyline[:, 0] - px, c.polyline[:, 1] - py)))


def _apply_tree_mask(c: RopeCandidate, tree_mask: np.ndarray) -> None:
    """Weight a candidate by how much of it lies on the tree mask and spans the trunk there."""
    H, W = tree_mask.shape
    p = c.polyline
    xi = np.clip(np.round(p[:, 0]).astype(int), 0, W - 1)
    yi = np.clip(np.round(p[:, 1]).astype(int), 0, H - 1)
    on = float(tree_mask[yi, xi].mean())
    l, r = _trunk_run(tree_mask, p, c.center_xy[0])
    if r >= l:
        c.span = float(np.clip((min(r, p[-1, 0]) - max(l, p[0, 0])) / max(r - l + 1, 1), 0.0, 1.0))
    else:
        c.span = 0.0
    c.score += float(np.log((0.2 + 0.8 * on) * (0.3 + 0.7 * c.span)))


def _dedupe(cands: list[RopeCandidate]) -> list[RopeCandidate]:
    """Drop candidates overlapping a better one (same band at two levels, or a sub-chain)."""
    out = []
    for c in cands:
        dup = False
        for o in out:
            x0, x1 = o.polyline[0, 0], o.polyline[-1, 0]
            if x0 - 2 <= c.center_xy[0] <= x1 + 2:
                yo = np.interp(c.center_xy[0], o.polyline[:, 0], o.polyline[:, 1])
                if abs(yo - c.center_xy[1]) < 2 + o.thickness_px + c.thickness_px:
                    dup = True
                    break
        if not dup:
            out.append(c)
    return out


def _trunk_run(tree_mask: np.ndarray, poly: np.ndarray, xc: float) -> tuple[int, int]:
    """Columns [l, r] of the tree-mask run along the (extended) rope curve that contains ``xc``."""
    H, W = tree_mask.shape
    xs = np.arange(W)
    ys = np.clip(np.round(np.interp(xs, poly[:, 0], poly[:, 1])).astype(int), 0, H - 1)
    on = tree_mask[ys, xs]
    x = int(np.clip(round(xc), 0, W - 1))
    if not on[x]:
        near = np.flatnonzero(on[max(0, x - 3):x + 4])
        if len(near) == 0:
            return 0, -1
        x = max(0, x - 3) + int(near[0])
    off = np.flatnonzero(~on)
    left = off[off < x]
    right = off[off > x]
    return (int(left[-1]) + 1 if len(left) else 0), (int(right[0]) - 1 if len(right) else W - 1)


def _refine(rgb: np.ndarray, c: RopeCandidate, tree_mask: np.ndarray | None) -> RopeDetection:
    """Full-resolution band mask, centre line and thickness around candidate ``c``."""
    H, W = rgb.shape[:2]
    T = max(c.thickness_px, 1.0)
    pad = int(np.ceil(3 * T + 8))
    x0 = max(0, int(np.floor(c.polyline[:, 0].min())) - pad)
    x1 = min(W, int(np.ceil(c.polyline[:, 0].max())) + pad + 1)
    y0 = max(0, int(np.floor(c.polyline[:, 1].min())) - pad)
    y1 = min(H, int(np.ceil(c.polyline[:, 1].max())) + pad + 1)
    F = redness_map(rgb[y0:y1, x0:x1])
    d = max(2, int(round(0.5 * T + 1.5)))
    R = line_contrast(F, ds=(d, d + 1), sigma_x=float(np.clip(0.5 * T, 1.0, 4.0)),
                      sigma_y=float(np.clip(0.2 * T, 0.5, 3.0)))
    xs = np.arange(x0, x1, dtype=np.float32)
    yy = np.arange(y0, y1, dtype=np.float32)[:, None]
    yc = np.interp(xs, c.polyline[:, 0], c.polyline[:, 1]).astype(np.float32)
    band = np.abs(yy - yc[None, :]) <= (T + 3)
    band &= ((xs >= c.polyline[0, 0] - 0.05 * c.length_px - 2) & (xs <= c.polyline[-1, 0] + 0.05 * c.length_px + 2))[None, :]
    vals = R[band]
    thr = max(0.4 * float(np.percentile(vals, 97)) if vals.size else 0.0, 0.01)
    m = band & (R > thr)
    # keep columns whose response is part of the band (drop isolated specks)
    colmax = np.where(m, R, 0).max(0)
    m &= (colmax > 1.5 * thr)[None, :]
    cols = np.flatnonzero(m.any(0))
    coef = None
    poly = c.polyline.copy()
    thick = c.thickness_px
    if len(cols) >= 3:
        w = np.where(m, R, 0)
        ws = w.sum(0)
        ymean = (w * yy).sum(0) / np.maximum(ws, 1e-9)
        xv, yv = xs[cols], ymean[cols]
        deg = 2 if len(cols) > 12 else 1
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
        poly = np.stack([px, py], 1).astype(np.float32)
        # thickness: full width at half maximum of the red-ness profile across the band
        thick = _profile_thickness(F, m, cols, coef, x0, y0, T)
        mm = np.zeros_like(m)
        mm[:, cols] = m[:, cols]
        m = mm
    mask = np.zeros((H, W), bool)
    mask[y0:y1, x0:x1] = m
    xc = 0.5 * (poly[0, 0] + poly[-1, 0])
    if tree_mask is not None:
        l, r = _trunk_run(tree_mask, poly, xc)
        if r >= l:
            xc = 0.5 * (l + r)
    if coef is not None:
        yc0 = float(np.polyval(coef, xc))
        slope = float(np.polyval(np.polyder(coef), xc))
    else:
        yc0 = float(np.interp(xc, poly[:, 0], poly[:, 1]))
        slope = c.direction[1] / max(c.direction[0], 1e-6)
    dvec = np.array([1.0, slope]) / np.hypot(1.0, slope)
    return RopeDetection(True, "", center_xy=(float(xc), yc0), direction=(float(dvec[0]), float(dvec[1])),
                         polyline=poly, thickness_px=float(thick), mask=mask, score=c.score)


def _profile_thickness(F: np.ndarray, m: np.ndarray, cols: np.ndarray, coef, x0: int, y0: int, T: float) -> float:
    """Median over columns of the FWHM (perpendicular to the band) of the red-ness profile."""
    Hh = F.shape[0]
    r = int(np.ceil(2 * T + 4))
    out = []
    dpoly = np.polyder(coef)
    for cc in cols[:: max(1, len(cols) // 60)]:
        yc = np.polyval(coef, cc + x0) - y0
        ya, yb = int(max(0, np.floor(yc - r))), int(min(Hh, np.ceil(yc + r) + 1))
        prof = F[ya:yb, cc]
        if len(prof) < 5:
            continue
        inner = np.abs(np.arange(ya, yb) - yc) <= T / 2 + 1
        if not inner.any() or inner.all():
            continue
        bg = float(np.median(prof[~inner]))
        pk = float(prof[inner].max())
        if pk - bg <= 1e-3:
            continue
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

        wdt = edge(b, b + 1) - edge(a, a - 1)
        out.append(wdt * np.cos(np.arctan(np.polyval(dpoly, cc + x0))))
    return float(np.median(out)) if out else float(T)


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
    P = np.asarray(polyline, np.float64)
    if len(P) < 2:
        return float("nan"), 0.0
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    L = float(s[-1])
    if L < 4:
        return float("nan"), 0.0
    ss = np.arange(0.5 * (1 - inner) * L, 0.5 * (1 + inner) * L, 1.0)
    cx, cy = np.interp(ss, s, P[:, 0]), np.interp(ss, s, P[:, 1])
    k = np.clip(np.searchsorted(s, ss) - 1, 0, len(P) - 2)
    t = (P[k + 1] - P[k]) / np.maximum(seg[k], 1e-9)[:, None]
    n = np.stack([-t[:, 1], t[:, 0]], 1)
    T = max(float(thickness_px), 1.0)
    r = 3.0 * T + 4.0
    off = np.arange(-r, r + 1e-6, 0.25)
    H, W = rgb.shape[:2]
    x0, x1 = int(max(0, np.floor(cx.min() - r - 2))), int(min(W, np.ceil(cx.max() + r + 3)))
    y0, y1 = int(max(0, np.floor(cy.min() - r - 2))), int(min(H, np.ceil(cy.max() + r + 3)))
    if x1 - x0 < 3 or y1 - y0 < 3:
        return float("nan"), 0.0
    F = redness_map(np.ascontiguousarray(rgb[y0:y1, x0:x1]))
    X = (cx[:, None] + off[None] * n[:, :1] - x0).astype(np.float32)
    Y = (cy[:, None] + off[None] * n[:, 1:] - y0).astype(np.float32)
    prof = cv2.remap(F, X, Y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).mean(0)
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
