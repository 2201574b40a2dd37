"""Classical detection of the red measuring rope tied around a stem at breast height.

The rope is a thin, red, roughly horizontal band (an ellipse arc of a ring seen from slightly
above or below) that crosses a trunk from edge to edge. Detection, all without a learned model:

1. **Red-ness** ``F = (R - max(G, B)) / (R + G + B + 30)`` - a chromaticity, so shading and exposure
   scale it little; computed on a copy downscaled to ``work_long_side`` pixels.
2. **Thin-line contrast** at three pyramid levels: after an anisotropic blur (along x), the
   red-ness of a pixel minus the larger of the red-ness ``d`` pixels above and below
   (``min(F(y) - F(y-d), F(y) - F(y+d))``). It is in red-ness units at every scale, is zero on
   the edges of red blobs and on uniformly reddish bark, and answers to bands up to ~60 deg from
   horizontal, so vertical paint marks and hanging rope ends give little.
3. **Segments**: connected components of the contrast map, described by moments (centre, axis
   angle, length, thickness = area / length); collinear pieces (a rope with a branch or a thin
   tree in front of it, or a knot) are merged when one extrapolates into the other.
4. **Candidates** are scored by contrast, length, continuity, band shape (thin relative to its
   length), hue (rope red rather than orange tape) and, with a ``tree_mask``, by how much of the
   trunk width they span. The best one is refined at full resolution in a small window.

Examples
--------
>>> det = detect_rope(rgb)                         # doctest: +SKIP
>>> if det: print(det.center_xy, det.thickness_px)  # doctest: +SKIP
... else: print(det.reason)
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np

__all__ = ["RopeDetection", "RopeCandidate", "detect_rope", "redness_map", "line_contrast"]


@dataclass
class RopeCandidate:
    """One scored rope hypothesis (full-resolution pixel coordinates).

    Attributes
    ----------
    center_xy : (x, y) middle of the band.
    direction : unit (dx, dy) of the band, dx >= 0.
    length_px, thickness_px : band extent along and across.
    score : higher is more rope-like (comparable between candidates of one photo).
    contrast : mean red-ness contrast of the band.
    coverage : fraction of the band's length where the band is seen (gaps = occluders).
    span : fraction of the trunk width the band spans (NaN without a tree mask).
    polyline : (N, 2) float32 centre line (x, y).
    """
    center_xy: tuple[float, float]
    direction: tuple[float, float]
    length_px: float
    thickness_px: float
    score: float
    contrast: float = 0.0
    coverage: float = 1.0
    span: float = float("nan")
    hue: float = 0.0
    polyline: np.ndarray | None = field(default=None, repr=False)
    _members: list = field(default_factory=list, repr=False)

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
    reason : why not found (or an ambiguity message naming the candidate positions); ``""`` if found.
    center_xy : (x, y) where the rope crosses the middle of the trunk, full-resolution pixels.
    direction : unit (dx, dy) of the band across the trunk (dx >= 0).
    polyline : (N, 2) float32 rope centre line (x, y) pixels.
    thickness_px : rope thickness across the band, pixels.
    mask : (H, W) bool rope pixels (all False when not found).
    score : score of the chosen candidate (0 when none).
    candidates : scored alternatives, best first (for ``--pick`` and error messages).
    ambiguous : two candidates scored within the ambiguity margin (then ``found`` is False).
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

    def __bool__(self) -> bool:
        return bool(self.found)


# ----------------------------------------------------------------------------- low-level maps

def redness_map(rgb: np.ndarray, offset: float = 30.0) -> np.ndarray:
    """Red chromaticity ``(R - max(G, B) - max(G - B, 0) / 2) / (R + G + B + offset)``.

    The ``G - B`` term lowers orange (sandy ground, flagging tape) relative to rope red.

    Parameters
    ----------
    rgb : (H, W, 3) uint8 RGB.
    offset : damps the noisy chromaticity of dark pixels.

    Returns
    -------
    (H, W) float32 in about [-0.5, 1].
    """
    f = rgb.astype(np.float32)
    R, G, B = f[..., 0], f[..., 1], f[..., 2]
    num = R - np.maximum(G, B) - 0.5 * np.maximum(G - B, 0)
    den = R + G + B
    den += offset
    num /= den
    return num


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
    (H, W) float32 >= 0, same units as ``F``.
    """
    G = cv2.GaussianBlur(F, (0, 0), sigmaX=sigma_x, sigmaY=sigma_y)
    H = G.shape[0]
    out = np.zeros_like(G)
    for d in ds:
        if d >= H:
            continue
        a = G[d:H - d] - G[:H - 2 * d]
        b = G[d:H - d] - G[2 * d:]
        np.minimum(a, b, out=a)
        np.maximum(out[d:H - d], a, out=out[d:H - d])
    return out


# ----------------------------------------------------------------------------- segments

_SEG_KEYS = ("cx", "cy", "theta", "length", "thick", "contrast", "red", "hue", "area", "level")


def _segments(R: np.ndarray, F: np.ndarray, hue: np.ndarray, thr: float, min_len: float, f: float):
    """Components of ``R > thr`` described by moments, in level-0 pixels (level pixels times ``f``).

    Returns a dict of (K,) arrays (see ``_SEG_KEYS``) or None.
    """
    m = (R > thr).astype(np.uint8)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    if n <= 1:
        return None
    w = stats[1:, cv2.CC_STAT_WIDTH]
    h = stats[1:, cv2.CC_STAT_HEIGHT]
    keep = np.flatnonzero((np.hypot(w, h) >= min_len) & (w >= 0.6 * h)) + 1
    if len(keep) == 0:
        return None
    remap = np.zeros(n, np.int32)
    remap[keep] = np.arange(1, len(keep) + 1)
    li = remap[lab]
    ys, xs = np.nonzero(li)
    li = li[ys, xs] - 1
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
    ct, st = np.cos(theta), np.sin(theta)
    u = dx * ct[li] + dy * st[li]
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
    seg = dict(cx=cx * f, cy=cy * f, theta=theta, length=length * f, thick=thick * f,
               contrast=np.bincount(li, wts, k) / cnt, red=np.bincount(li, F[ys, xs], k) / cnt,
               hue=np.bincount(li, hue[ys, xs], k) / cnt, area=cnt * f * f)
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
              & (dth < np.deg2rad(40)) & (np.abs(seg["hue"][:, None] - seg["hue"][None, :]) < 0.15))
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
    """All runs of up to ``max_run`` consecutive segments of each chain, best band score first."""
    out, scores = [], []
    for ch in chains:
        ch = np.asarray(ch)
        n = len(ch)
        a = seg["area"][ch]
        cs = lambda v: np.concatenate([[0.0], np.cumsum(v)])
        A, CL = cs(a), cs(seg["length"][ch])
        AC, AH = cs(a * seg["contrast"][ch]), cs(a * seg["hue"][ch])
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
        for q in np.flatnonzero(s > 0):
            out.append(list(ch[i[q]:j[q]]))
            scores.append(s[q])
    order = np.argsort(-np.asarray(scores)) if scores else []
    return [out[q] for q in order]


def _band_score(contrast, length, thick, coverage, hue):
    """Score from the band alone: contrast, length, continuity, thinness, red (not orange) hue."""
    T = np.maximum(thick, 0.7)
    shape = np.clip((length / T - 3.0) / 10.0, 0.0, 1.0)
    hue_pen = np.clip(1.0 - 3.0 * np.maximum(0.0, hue - 0.2), 0.25, 1.0)
    return contrast * np.sqrt(length) * (0.3 + 0.7 * coverage) * shape * hue_pen


def _make_candidate(seg: dict, idx: list[int]) -> RopeCandidate:
    """Fit a band (quadratic centre line) through member segments ``idx`` (level-0 pixels)."""
    idx = np.asarray(idx)
    xl, yl, xr, yr = seg["xl"][idx], seg["yl"][idx], seg["xr"][idx], seg["yr"][idx]
    cx, cy = seg["cx"][idx], seg["cy"][idx]
    a = seg["area"][idx]
    x0, x1 = float(xl.min()), float(xr.max())
    px = np.concatenate([xl, cx, xr])
    py = np.concatenate([yl, cy, yr])
    pw = np.concatenate([a, 2 * a, a]) * np.tile(seg["contrast"][idx], 3)
    xm = float(np.average(px, weights=pw))
    deg = 2 if len(idx) >= 2 else 1
    A = np.stack([np.ones_like(px), px - xm, (px - xm) ** 2][:deg + 1], 1)
    sw = np.sqrt(pw)
    coef, *_ = np.linalg.lstsq(A * sw[:, None], py * sw, rcond=None)
    if deg == 1:
        coef = np.append(coef, 0.0)
    xs = np.linspace(x0, x1, 24)
    ys = coef[0] + coef[1] * (xs - xm) + coef[2] * (xs - xm) ** 2
    arc = float(np.hypot(np.diff(xs), np.diff(ys)).sum()) + 1.0
    covered = float(np.sum(seg["length"][idx]))
    area = float(a.sum())
    xc = 0.5 * (x0 + x1)
    yc = coef[0] + coef[1] * (xc - xm) + coef[2] * (xc - xm) ** 2
    d = np.array([1.0, coef[1] + 2 * coef[2] * (xc - xm)])
    d /= np.linalg.norm(d)
    c = RopeCandidate(center_xy=(float(xc), float(yc)), direction=(float(d[0]), float(d[1])),
                      length_px=arc, thickness_px=area / max(covered, 1.0), score=0.0,
                      contrast=float(np.average(seg["contrast"][idx], weights=a)),
                      coverage=min(1.0, covered / arc), hue=float(np.average(seg["hue"][idx], weights=a)),
                      polyline=np.stack([xs, ys], 1).astype(np.float32))
    c._members = [int(i) for i in idx]
    c.level = int(np.round(np.average(seg["level"][idx], weights=a)))
    c.pre = _prescore(c)
    return c


def _prescore(c: RopeCandidate) -> float:
    """Band-only score of a fitted candidate (see :func:`_band_score`)."""
    return float(_band_score(c.contrast, c.length_px, c.thickness_px, c.coverage, c.hue))


def _maxfilt(v: np.ndarray, r: int) -> np.ndarray:
    """Running maximum of a 1-D array over a window of half width ``r``."""
    if r <= 0:
        return v
    return cv2.dilate(v.astype(np.float32)[None, :], np.ones((1, 2 * r + 1), np.uint8),
                      borderType=cv2.BORDER_REPLICATE)[0]


def _context(c: RopeCandidate, gray: np.ndarray, mask0: np.ndarray) -> None:
    """Trunk context of a candidate on the working image (level-0 pixels).

    ``edge``: both band ends lie on a vertical intensity edge (the trunk silhouette) that holds
    above and below the band, in [0, 1]. ``clutter``: other thin red lines on the trunk area
    just above and below the band, relative to the band's own area.
    """
    H, W = gray.shape
    L = c.length_px
    T = max(c.thickness_px, 1.0)
    p = c.polyline
    hs = int(np.clip(0.2 * L, 4, 80))                 # height of each of the 4 sub-strips
    a = int(np.clip(0.05 * L, 1, 16))                 # half width of the step box
    s = int(np.clip(0.2 * L, 3, 100))                 # search range around each band end
    edges = []
    for (xe, ye) in (p[0], p[-1]):
        xa = int(round(xe)) - s - a - 1
        xb = int(round(xe)) + s + a + 2
        prof, reach = [], []
        for ya, dist in ((ye - T - 1 - 2 * hs, 1.5 * hs), (ye - T - 1 - hs, 0.5 * hs),
                         (ye + T + 1, 0.5 * hs), (ye + T + 1 + hs, 1.5 * hs)):
            ya = int(round(ya))
            if ya < 0 or ya + hs > H or xa < 0 or xb > W:
                continue
            prof.append(gray[ya:ya + hs, xa:xb].mean(0))
            reach.append(int(round(0.27 * (dist + T))))        # trunk lean / tilt up to 15 deg
        if len(prof) < 2:
            edges.append(0.0)
            continue
        P = np.cumsum(np.pad(np.stack(prof), ((0, 0), (1, 0))), 1)
        n = P.shape[1] - 1
        x = np.arange(a, n - a)
        D = (P[:, x + a] - 2 * P[:, x] + P[:, x - a]) / a      # right box mean - left box mean
        best = 0.0
        for sg in (1.0, -1.0):
            Ds = np.stack([_maxfilt(sg * d, r) for d, r in zip(D, reach)])
            e = np.maximum(0.0, Ds.min(0))
            best = max(best, float(e.max()) if e.size else 0.0)
        edges.append(best / (best + 6.0))
    c.edge = float(np.sqrt(edges[0] * edges[1]))
    c.edges = edges
    # clutter on the trunk face above/below the band
    x0 = int(np.clip(round(p[0, 0] + 0.1 * L), 0, W - 1))
    x1 = int(np.clip(round(p[-1, 0] - 0.1 * L), 0, W))
    ya = int(np.clip(round(p[:, 1].min() - 0.5 * L), 0, H - 1))
    yb = int(np.clip(round(p[:, 1].max() + 0.5 * L + 1), 0, H))
    if x1 > x0 and yb > ya:
        sub = mask0[ya:yb, x0:x1]
        yc = np.interp(np.arange(x0, x1), p[:, 0], p[:, 1])
        band = np.abs(np.arange(ya, yb)[:, None] - yc[None, :]) <= T + 2
        cnt = float(np.count_nonzero(sub & ~band))
        c.clutter = cnt / max(L * T, 1.0)
    else:
        c.clutter = 0.0


# ----------------------------------------------------------------------------- detector

def detect_rope(rgb: np.ndarray, tree_mask: np.ndarray | None = None, *,
                pick_xy: tuple[float, float] | None = None,
                height_check: Callable[[RopeCandidate], bool] | None = None,
                work_long_side: int = 1600, min_contrast: float = 0.025, min_score: float = 0.0,
                ambiguity_ratio: float = 0.75, max_candidates: int = 40,
                max_segments: int = 500) -> RopeDetection:
    """Find the red rope tied around a trunk.

    Parameters
    ----------
    rgb : (H, W, 3) uint8 RGB photo.
    tree_mask : (H, W) bool trunk/tree pixels, optional; candidates that span a trunk's width
        are preferred and bands off the mask are penalised.
    pick_xy : (x, y) full-resolution pixel; choose the candidate nearest to it (resolves ambiguity).
    height_check : optional callable ``candidate -> bool`` from the pipeline (e.g. "is this about
        1.3 m above the ground?"); candidates for which it returns False are dropped.
    work_long_side : candidates are searched on a copy downscaled to this long side.
    min_contrast : minimum mean red-ness contrast of a band.
    min_score : candidates scoring below are ignored.
    ambiguity_ratio : a second candidate scoring at least this fraction of the best makes the
        result ambiguous (``found=False``, ``ambiguous=True``) unless ``pick_xy`` is given.
    max_candidates : how many of the best band candidates get the (costlier) context check.
    max_segments : at most this many line pieces (the most contrasted) are linked into bands.

    Returns
    -------
    RopeDetection
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
    s = min(1.0, work_long_side / max(H, W))
    small = rgb if s >= 1.0 else cv2.resize(rgb, (round(W * s), round(H * s)), interpolation=cv2.INTER_AREA)
    sx, sy = W / small.shape[1], H / small.shape[0]
    F = redness_map(small)
    f = small.astype(np.float32)
    hue = (f[..., 1] - f[..., 2]) / (f[..., 0] + 8.0)            # orange-ness: (G - B) / R
    gray = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY).astype(np.float32)
    lap("prepare")

    thr = 0.6 * min_contrast
    segs, mask0 = [], None
    for level in range(3):
        R = line_contrast(F)
        if level == 0:
            mask0 = R > thr
        sg = _segments(R, F, hue, thr=thr, min_len=5.0, f=2.0 ** level)
        if sg is not None:
            sg["level"] = np.full(len(sg["cx"]), level)
            segs.append(sg)
        if level < 2 and min(F.shape) >= 64:
            F, hue = cv2.pyrDown(F), cv2.pyrDown(hue)
        else:
            break
    lap("lines")
    none = RopeDetection(False, "no red rope found (no thin red band crossing a trunk)", timings_ms=tm)
    if not segs:
        return none
    seg = {k: np.concatenate([g[k] for g in segs]) for k in _SEG_KEYS}
    # drop specks; bound the pairwise linking cost
    keep = (seg["contrast"] >= 0.5 * min_contrast) & ((seg["length"] >= 10) | (seg["contrast"] >= min_contrast))
    seg = {k: v[keep] for k, v in seg.items()}
    if len(seg["cx"]) > max_segments:
        top = np.argsort(-seg["contrast"] * np.sqrt(seg["length"]))[:max_segments]
        seg = {k: v[top] for k, v in seg.items()}
    # rank every run of up to 8 consecutive linked segments by the band-only score, fit the best
    runs = _runs(seg, _link(seg), min_contrast)
    cands = [_make_candidate(seg, idx) for idx in runs[:3 * max_candidates]]
    cands = [c for c in cands if c.pre > 0]
    cands.sort(key=lambda c: -c.pre)
    cands = _dedupe(cands, key="pre")[:max_candidates]
    lap("group")
    for c in cands:
        _context(c, gray, mask0)
        c.score = _final_score(c)
    # to full resolution
    for c in cands:
        c.polyline = c.polyline * np.array([sx, sy], np.float32)
        c.center_xy = (c.center_xy[0] * sx, c.center_xy[1] * sy)
        c.length_px *= sx
        c.thickness_px *= sy
    if tree_mask is not None:
        for c in cands:
            _apply_tree_mask(c, tree_mask)
    if height_check is not None:
        cands = [c for c in cands if height_check(c)]
    cands = [c for c in cands if c.score > min_score]
    cands.sort(key=lambda c: -c.score)
    cands = _dedupe(cands, key="score")
    lap("score")
    if not cands:
        return none
    best = cands[0]
    if pick_xy is not None:
        px, py = pick_xy
        best = min(cands[:20], key=lambda c: _dist_to(c, px, py))
    elif len(cands) > 1 and cands[1].score >= ambiguity_ratio * best.score:
        c1, c2 = cands[0], cands[1]
        msg = (f"two rope candidates at ({c1.center_xy[0]:.0f},{c1.center_xy[1]:.0f}) and "
               f"({c2.center_xy[0]:.0f},{c2.center_xy[1]:.0f}); choose one with --pick X,Y")
        return RopeDetection(False, msg, candidates=cands, ambiguous=True, timings_ms=tm)
    det = _refine(rgb, best, tree_mask)
    det.candidates = cands
    lap("refine")
    tm["total"] = round(1000 * (time.perf_counter() - t0), 2)
    det.timings_ms = tm
    return det


def _final_score(c: RopeCandidate) -> float:
    return float(c.pre * (0.15 + 0.85 * c.edge) / (1.0 + c.clutter))


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
    c.score *= (0.2 + 0.8 * on) * (0.3 + 0.7 * c.span)


def _dedupe(cands: list[RopeCandidate], key: str = "score") -> list[RopeCandidate]:
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
