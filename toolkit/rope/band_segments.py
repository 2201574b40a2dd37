"""The band detector's pieces and bands: thin-line pieces described by moments, pieces linked
end to end, runs of linked pieces worth fitting, and the quadratic band fitted through a run;
imported by :mod:`.band`.

Pieces that extrapolate into each other (a rope behind a branch or a thin stem, a knot) are
linked end to end; runs of linked pieces are fitted with a quadratic centre line. The best runs
by a cheap band score get the full score, plus some from image squares none of those occupies
(:func:`diverse_runs`): a patch of red clutter (leaf litter, berries) would otherwise take the
whole budget from a faint rope elsewhere. All lengths here are working-image (level-0) pixels.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

__all__ = ["SEG_KEYS", "BandFit", "line_pieces", "piece_ends", "link_pieces", "band_runs", "diverse_runs",
           "cheap_band_score", "fit_band"]

#: the per-piece arrays of a piece table (see :func:`line_pieces`)
SEG_KEYS = ("cx", "cy", "theta", "length", "thick", "contrast", "hue", "red", "area", "level")


@dataclass(frozen=True)
class BandFit:
    """A band fitted through linked pieces, working-image pixels.

    Attributes
    ----------
    center_xy : (x, y) middle of the band; direction : unit (dx, dy) there, dx > 0.
    length_px : arc length of the centre line; thickness_px : pieces' area over their length.
    contrast, hue, red : area-weighted means of the pieces' contrast, ``(G - B) / R`` and red-ness.
    coverage : fraction of the band's length covered by pieces.
    polyline : (24, 2) float32 centre line (x, y).
    level : pyramid level (area-weighted, rounded); resid : weighted residual of the fit;
    members : number of pieces; deep : scored beyond the band-score budget (:func:`diverse_runs`).
    """
    center_xy: tuple[float, float]
    direction: tuple[float, float]
    length_px: float
    thickness_px: float
    contrast: float
    coverage: float
    hue: float
    red: float
    polyline: np.ndarray = field(repr=False)
    level: int = 0
    resid: float = 0.0
    members: int = 1
    deep: bool = False


def line_pieces(R: np.ndarray, F: np.ndarray, rgb: np.ndarray, thr: float, min_len: float, level: int):
    """Components of ``R > thr`` described by moments, in level-0 pixels.

    Parameters
    ----------
    R : (h, w) float32 thin-line contrast of pyramid level ``level``; F : (h, w) its red-ness;
    rgb : (h, w, 3) uint8 that level's image.
    thr : contrast level of piece pixels; min_len : shortest piece, pixels of the level.

    Returns
    -------
    dict of (K,) arrays (keys :data:`SEG_KEYS`), or None when no piece is band-like.
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
    return _piece_moments(R, F, rgb, ys, xs, li, len(keep), min_len, f, level)


def _piece_moments(R, F, rgb, ys, xs, li, k: int, min_len: float, f: float, level: int):
    """The piece table of labelled line pixels ``(ys, xs)`` (piece ``li`` of ``k``)."""
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


def piece_ends(seg: dict) -> dict:
    """The piece table with each piece's end points and unit direction (dx >= 0) added:
    ``xl, yl, xr, yr, ux, uy`` (a new dict)."""
    cx, cy, th, L = seg["cx"], seg["cy"], seg["theta"], seg["length"]
    ct, st = np.cos(th), np.sin(th)
    sgn = np.where(ct < 0, -1.0, 1.0)
    ux, uy = ct * sgn, st * sgn
    xl, yl = cx - 0.5 * L * ux, cy - 0.5 * L * uy
    xr, yr = cx + 0.5 * L * ux, cy + 0.5 * L * uy
    return dict(seg, xl=xl, yl=yl, xr=xr, yr=yr, ux=ux, uy=uy)


def link_pieces(seg: dict) -> list[list[int]]:
    """Chains of pieces linked end to end (a band broken by occluders, a knot or noise).

    Parameters
    ----------
    seg : piece table with its ends (:func:`piece_ends`).

    Returns
    -------
    list of chains, each a list of piece indices from left to right.
    """
    n = len(seg["cx"])
    if n == 0:
        return []
    nxt = -np.ones(n, int)
    prv = -np.ones(n, int)
    if n > 1:
        ii, jj, cost = _link_pairs(seg)
        for q in np.argsort(cost):
            i, j = ii[q], jj[q]
            if nxt[i] < 0 and prv[j] < 0 and not _reaches(prv, i, j):
                nxt[i] = j
                prv[j] = i
    chains = []
    for s in np.flatnonzero(prv < 0):
        ch = [int(s)]
        while nxt[ch[-1]] >= 0:
            ch.append(int(nxt[ch[-1]]))
        chains.append(ch)
    return chains


def _link_pairs(seg: dict):
    """Pairs ``(i, j)`` where piece i's right end extrapolates into piece j's left end, and the
    cost of each link (off-line error over tolerance plus gap over length)."""
    L, T = seg["length"], seg["thick"]
    xl, yl, xr, yr = seg["xl"], seg["yl"], seg["xr"], seg["yr"]
    slope = seg["uy"] / np.maximum(seg["ux"], 0.3)
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
    return ii, jj, err[ii, jj] / tol[ii, jj] + gpos[ii, jj] / lsum[ii, jj]


def _reaches(prv: np.ndarray, i: int, j: int) -> bool:
    """Whether walking back from piece ``i`` along the links ``prv`` meets piece ``j`` (a link
    i -> j would close a cycle)."""
    k = i
    while k >= 0:
        if k == j:
            return True
        k = prv[k]
    return False


def band_runs(seg: dict, chains: list[list[int]], min_contrast: float, max_run: int = 8) -> list[list[int]]:
    """Runs of up to ``max_run`` consecutive linked pieces worth fitting, best band score first.

    Per chain: its 3 best runs and its 3 best single pieces (a sub-run may be the rope and the
    whole chain the rope plus collinear clutter, or the reverse).
    """
    out, scores = [], []
    single = np.array([len(ch) == 1 for ch in chains], bool)
    if single.any():                                   # vectorised: most chains are one piece
        q = np.array([ch[0] for ch, s1 in zip(chains, single) if s1])
        s = cheap_band_score(seg["contrast"][q], seg["length"][q], seg["thick"][q], 1.0, seg["hue"][q])
        s[(seg["contrast"][q] < min_contrast) | (seg["length"][q] < 8)] = 0.0
        for k in np.flatnonzero(s > 0):
            out.append([int(q[k])])
            scores.append(s[k])
    for ch in (ch for ch, s1 in zip(chains, single) if not s1):
        for run, s in _chain_runs(seg, np.asarray(ch), min_contrast, max_run):
            out.append(run)
            scores.append(s)
    order = np.argsort(-np.asarray(scores)) if scores else []
    return [out[q] for q in order]


def _chain_runs(seg: dict, ch: np.ndarray, min_contrast: float, max_run: int):
    """``(run, band score)`` of a chain's 3 best runs and 3 best single pieces (score > 0)."""
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
    s = cheap_band_score(con, ext, area / np.maximum(covered, 1.0), np.minimum(1.0, covered / ext), hue)
    s[(con < min_contrast) | (ext < 8)] = 0.0
    sel = list(np.argsort(-s)[:3])
    one = np.flatnonzero(j - i == 1)
    sel += list(one[np.argsort(-s[one])[:3]])
    return [([int(v) for v in ch[i[q]:j[q]]], s[q]) for q in dict.fromkeys(sel) if s[q] > 0]


def diverse_runs(seg: dict, runs: list[list[int]], n: int, cell: float, extra: int,
                 per_cell: int = 2) -> list[list[int]]:
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


def cheap_band_score(contrast, length, thick, coverage, hue):
    """Cheap ranking score from the band alone (contrast, length, continuity, thinness, hue)."""
    T = np.maximum(thick, 0.7)
    shape = np.clip((length / T - 3.0) / 10.0, 0.0, 1.0)
    hue_pen = np.clip(1.0 - 3.0 * np.maximum(0.0, hue - 0.2), 0.25, 1.0)
    return contrast * np.sqrt(length) * (0.3 + 0.7 * coverage) * shape * hue_pen


def fit_band(seg: dict, idx: list[int], deep: bool = False) -> BandFit:
    """Fit a band (quadratic centre line) through member pieces ``idx`` (level-0 pixels).

    Parameters
    ----------
    seg : piece table with its ends (:func:`piece_ends`).
    idx : the member pieces, left to right.
    deep : recorded on the fit (scored beyond the band-score budget).
    """
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
    return BandFit(
        center_xy=(float(xc), float(yc)), direction=(float(d[0]), float(d[1])),
        length_px=arc, thickness_px=area / max(covered, 1.0),
        contrast=float(np.average(seg["contrast"][idx], weights=a)), coverage=min(1.0, covered / arc),
        hue=float(np.average(seg["hue"][idx], weights=a)), red=float(np.average(seg["red"][idx], weights=a)),
        polyline=np.stack([xs, ys], 1).astype(np.float32),
        level=int(np.round(np.average(seg["level"][idx], weights=a))), resid=resid, members=len(idx), deep=deep)
