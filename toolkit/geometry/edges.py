"""Sub-pixel silhouette edges of a stem across the rope, and the stem's image axis.

The tree mask (from the segmenter, possibly coarse) says roughly where the stem's left and
right borders are; the photo's gradient along lines parallel to the rope places them to a
fraction of a pixel. Lines are sampled above and below the rope band (the rope itself bulges
the silhouette), and straight lines fitted through the edge points give the edges at the
rope's height.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["TrunkEdges", "trunk_edges", "trace_stem_base", "track_stem_base", "rope_row_contrast", "combine_edges",
           "REASON_OUT_OF_PHOTO"]

#: :attr:`TrunkEdges.reason` when a side of the stem lies outside the photo at the rope
REASON_OUT_OF_PHOTO = ("the stem runs out of the photo at the rope (step back or re-frame so that both "
                       "sides of the stem show)")


@dataclass
class TrunkEdges:
    """Left/right silhouette edge points at the rope (image pixels) and quality figures.

    Falsy when the edges could not be found (``reason`` says why).
    """
    left_xy: np.ndarray | None = None      # (2,)
    right_xy: np.ndarray | None = None     # (2,)
    width_px: float = np.nan
    along: np.ndarray | None = None        # (2,) unit image direction of the stem (down the photo)
    across: np.ndarray | None = None       # (2,) unit direction left -> right
    edge_rms_px: float = np.inf            # scatter of edge points about the fitted lines
    n_lines: int = 0
    points: dict = field(default_factory=dict)
    reason: str = ""

    def __bool__(self) -> bool:
        return self.left_xy is not None


def _sample(img: np.ndarray, xs: np.ndarray, ys: np.ndarray, nearest: bool = False) -> np.ndarray:
    import cv2
    mx = xs.astype(np.float32)
    my = ys.astype(np.float32)
    return cv2.remap(img, mx, my, cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def _subpixel_peak(g: np.ndarray, i: int) -> float:
    if 0 < i < len(g) - 1:
        a, b, c = g[i - 1], g[i], g[i + 1]
        den = a - 2 * b + c
        if den < 0:
            return i + 0.5 * (a - c) / den
    return float(i)


def trunk_edges(gray: np.ndarray, tree_mask: np.ndarray, center_xy, across_dir, *,
                rope_half_px: float = 1.5, search_px: float = 3.0, n_lines: int = 16) -> TrunkEdges:
    """Find the stem's silhouette edges at the rope.

    Parameters
    ----------
    gray : (H, W) float32 photo intensity (any scale).
    tree_mask : (H, W) bool mask of the roped tree (same size).
    center_xy : (2,) rope centre on the stem (pixels).
    across_dir : (2,) direction of the rope band across the stem.
    rope_half_px : half thickness of the rope (pixels); lines avoid ``3 x`` that band.
    search_px : how far (pixels) around the mask border the gradient peak is searched.
    n_lines : number of sampling lines (half above, half below the rope).

    Returns
    -------
    TrunkEdges
    """
    H, W = gray.shape
    c = np.asarray(center_xy, np.float64)
    u = np.asarray(across_dir, np.float64)
    u = u / np.linalg.norm(u)
    if u[0] < 0:
        u = -u
    a = np.array([-u[1], u[0]])                 # along the stem
    if a[1] < 0:
        a = -a                                  # pointing down the photo
    tm_ = np.asarray(tree_mask)
    m8 = tm_.view(np.uint8) if tm_.dtype == bool else tm_.astype(np.uint8)      # (no copy of a bool mask)
    # half-width from the mask along the rope line
    s = np.arange(-min(W, 4000) / 2, min(W, 4000) / 2, 1.0)
    xs, ys = c[0] + s * u[0], c[1] + s * u[1]
    inside = (xs >= 0) & (xs < W - 1) & (ys >= 0) & (ys < H - 1)
    mk = np.zeros(len(s), np.uint8)
    mk[inside] = _sample(m8, xs[inside][None], ys[inside][None], nearest=True)[0]
    i0 = int(np.argmin(np.abs(s)))
    if not mk[max(0, i0 - 2):i0 + 3].any():
        return TrunkEdges(reason="rope centre is not on the tree mask")
    # contiguous run around the centre
    run = mk[i0] or mk[max(0, i0 - 2):i0 + 3].any()
    lo = i0
    while lo > 0 and mk[lo - 1]:
        lo -= 1
    hi = i0
    while hi < len(s) - 1 and mk[hi + 1]:
        hi += 1
    half = max(2.0, (s[hi] - s[lo]) / 2)
    del run
    step = max(1.0, 2.0 * rope_half_px)
    offs = []
    k = 0
    while len(offs) < n_lines and k < 4 * n_lines:
        t = (1.5 + k * 0.9) * step + 2.0
        offs += [-t, t]
        k += 1
    offs = np.array(sorted(offs, key=abs)[:n_lines])
    lefts, rights = [], []
    n_out = 0       # stem borders that fall outside the photo
    S = np.arange(-half * 1.6 - search_px - 3, half * 1.6 + search_px + 3, 0.25)
    gs = np.asarray(gray, np.float32)        # (no copy when it is float32 already)
    for t in offs:
        base = c + t * a
        xs, ys = base[0] + S * u[0], base[1] + S * u[1]
        ok = (xs >= 1) & (xs < W - 2) & (ys >= 1) & (ys < H - 2)
        if ok.mean() < 0.25:
            continue
        # (a wide stem near the photo's border: the line may leave the photo beyond the stem;
        # only the windows around the two borders have to be inside it)
        prof = _sample(gs, xs[None], ys[None])[0]
        mk = _sample(m8, xs[None], ys[None], nearest=True)[0].astype(bool) & ok
        j0 = int(np.argmin(np.abs(S)))
        if not mk[max(0, j0 - 8):j0 + 9].any():
            continue
        # mask borders of the run around the centre
        jj = j0 if mk[j0] else (j0 - 8 + int(np.argmax(mk[max(0, j0 - 8):j0 + 9])))
        l_, r_ = jj, jj
        while l_ > 0 and mk[l_ - 1]:
            l_ -= 1
        while r_ < len(S) - 1 and mk[r_ + 1]:
            r_ += 1
        # gradient magnitude (profile smoothed with sigma ~0.75 px = 3 samples)
        ker = np.exp(-0.5 * (np.arange(-9, 10) / 3.0) ** 2)
        ker /= ker.sum()
        sm = np.convolve(prof, ker, mode="same")
        g = np.abs(np.gradient(sm))
        w = int(search_px * 4)
        for border, store in ((l_ - 2, lefts), (r_ + 2, rights)):     # mask border at half-sample
            a0, a1 = max(1, border - w), min(len(S) - 2, border + w)
            if a1 <= a0 or not ok[a0 - 1:a1 + 1].all():
                n_out += 1      # the stem runs out of the photo on this side
                continue
            # gradient peak, weighted by closeness to the mask border (prior)
            prior = np.exp(-0.5 * ((np.arange(a0, a1) - border) / (0.5 * w)) ** 2)
            j = a0 + int(np.argmax(g[a0:a1] * prior))
            pos = _subpixel_peak(g, j)
            sval = np.interp(pos, np.arange(len(S)), S)
            store.append((t, sval, float(g[j])))
    if len(lefts) < 3 or len(rights) < 3:
        if n_out >= 3:
            return TrunkEdges(reason=REASON_OUT_OF_PHOTO)
        return TrunkEdges(reason="stem edges not found around the rope")
    L = np.array(lefts)
    R = np.array(rights)

    def robust_line(P):
        # fit s = p0 + p1 * t, drop points > 3 MAD, refit
        keep = np.ones(len(P), bool)
        for _ in range(3):
            A = np.c_[np.ones(keep.sum()), P[keep, 0]]
            coef, *_ = np.linalg.lstsq(A, P[keep, 1], rcond=None)
            r = P[:, 1] - (coef[0] + coef[1] * P[:, 0])
            mad = np.median(np.abs(r[keep])) + 0.05
            new = np.abs(r) < 3.5 * mad
            if new.sum() < 3 or (new == keep).all():
                break
            keep = new
        rr = r[keep]
        return coef, float(np.sqrt(np.mean(rr ** 2))), keep

    cl, rms_l, kl = robust_line(L)
    cr, rms_r, kr = robust_line(R)
    sl, sr = cl[0], cr[0]
    left = c + sl * u
    right = c + sr * u
    # stem direction from the mid-line slope
    mid_slope = 0.5 * (cl[1] + cr[1])
    along = a + mid_slope * u
    along /= np.linalg.norm(along)
    return TrunkEdges(left_xy=left, right_xy=right, width_px=float(sr - sl), along=along, across=u,
                      edge_rms_px=float(max(rms_l, rms_r)), n_lines=int(min(kl.sum(), kr.sum())),
                      points=dict(left=np.array([c + t * a + s_ * u for t, s_, _ in L[kl]]),
                                  right=np.array([c + t * a + s_ * u for t, s_, _ in R[kr]])))


def rope_row_contrast(redness: np.ndarray, center_xy, rope_dir, across, along, s: np.ndarray, *,
                      rope_half_px: float, sag_px: float = 0.0) -> np.ndarray:
    """Red-ness of the rope's row minus that of the rows beside it, at positions across the stem.

    The rope's centre line is the straight line through ``center_xy`` along ``rope_dir``; the
    position ``s`` is measured along ``across`` (the direction of the stem's cross-section).
    Where the rope is, its row is redder than the rows ``3-6`` rope half-thicknesses above and
    below; where the stem carries no rope (e.g. a neighbouring trunk the segmenter merged in),
    the two are alike.

    Parameters
    ----------
    redness : (H, W) float32 red-ness map (:func:`monodbh.toolkit.rope.redness_map`).
    center_xy : (2,) rope centre (pixels); rope_dir : (2,) rope direction.
    across, along : (2,) unit directions across and along the stem.
    s : (N,) positions along ``across`` from ``center_xy`` (pixels).
    rope_half_px : half thickness of the rope (pixels).
    sag_px : how far the rope may bend away from the straight line (pixels; a rope seen from
        above or below is an arc).

    Returns
    -------
    (N,) float32: per position, the largest red-ness within the rope's rows minus the median
    red-ness of the reference rows.

    Examples
    --------
    >>> c = rope_row_contrast(F, (320, 240), (1, 0), (1, 0), (0, 1), np.arange(-10, 10.0),
    ...                       rope_half_px=1.5)        # doctest: +SKIP
    """
    d = np.asarray(rope_dir, np.float64)
    d = d / np.linalg.norm(d)
    u = np.asarray(across, np.float64)
    a = np.asarray(along, np.float64)
    if d @ u < 0:
        d = -d
    s = np.asarray(s, np.float64)
    base = np.asarray(center_xy, np.float64)[None] + (s / max(float(d @ u), 0.3))[:, None] * d[None]
    h = max(0.5, float(rope_half_px))
    reach = 1.5 * h + 1.0 + sag_px
    t_in = np.arange(-reach, reach + 1e-6, 0.5)
    t_ref = np.arange(3 * h + 2 + sag_px, 6 * h + 4 + sag_px, 1.0)
    t_ref = np.r_[-t_ref, t_ref]

    def rows(ts):
        P = base[:, None, :] + ts[None, :, None] * a[None, None, :]
        return _sample(redness, P[..., 0], P[..., 1])

    return (rows(t_in).max(1) - np.median(rows(t_ref), 1)).astype(np.float32)


def combine_edges(left: TrunkEdges, right: TrunkEdges, frame: TrunkEdges | None = None) -> TrunkEdges:
    """Edges with the left side of ``left`` and the right side of ``right``, both found at the
    same rope; the stem and cross-section directions are ``frame``'s (default ``left``'s).

    Returns
    -------
    TrunkEdges
    """
    frame = frame or left
    u = frame.across
    width = float((right.right_xy - left.left_xy) @ u)
    return TrunkEdges(left_xy=left.left_xy, right_xy=right.right_xy, width_px=width, along=frame.along, across=u,
                      edge_rms_px=max(left.edge_rms_px, right.edge_rms_px), n_lines=min(left.n_lines, right.n_lines),
                      points=dict(left=left.points.get("left"), right=right.points.get("right")))


def trace_stem_base(tree_mask: np.ndarray, ground_mask: np.ndarray, start_xy, along, width_px: float,
                    *, max_gap_px: int = 3) -> tuple[np.ndarray | None, str]:
    """Walk down the stem's image mid-line from the rope to where the stem meets the ground.

    Returns ``(base_xy, status)`` where status is ``"ground"`` when stem pixels end on ground
    pixels, ``"occluded"`` when they end on something else (bush, another tree), ``"edge"`` at
    the photo border; ``base_xy`` is None unless status is ``"ground"``.
    """
    H, W = tree_mask.shape
    p = np.asarray(start_xy, np.float64)
    a = np.asarray(along, np.float64)
    a = a / np.linalg.norm(a)
    perp = np.array([-a[1], a[0]])
    half = max(1.0, 0.25 * width_px)
    last_in = None
    gap = 0
    t = 0.0
    while True:
        q = p + t * a
        if not (0 <= q[0] < W and 0 <= q[1] < H):
            return None, "edge"
        pts = q[None] + np.linspace(-half, half, 5)[:, None] * perp[None]
        xi = np.clip(np.round(pts[:, 0]).astype(int), 0, W - 1)
        yi = np.clip(np.round(pts[:, 1]).astype(int), 0, H - 1)
        if tree_mask[yi, xi].mean() >= 0.5:
            last_in = q
            gap = 0
        else:
            gap += 1
            if gap > max_gap_px and last_in is not None:
                below = last_in + (max_gap_px + 2) * a
                bx = int(np.clip(round(below[0]), 0, W - 1))
                by = int(np.clip(round(below[1]), 0, H - 1))
                win = ground_mask[max(0, by - 2):by + 3, max(0, bx - 2):bx + 3]
                if win.size and win.mean() >= 0.5:
                    return last_in, "ground"
                return None, "occluded"
        t += 1.0
        if t > 4 * max(H, W):
            return None, "edge"


def _peak_near(gray: np.ndarray, p: np.ndarray, u: np.ndarray, half: float) -> tuple[float, float, float]:
    """Strongest intensity edge on the segment ``p + s u, |s| <= half``: ``(s, gradient, snr)``.

    The profile is sampled every 0.25 px, smoothed (sigma 0.75 px) and differentiated; the
    peak is refined to sub-sample precision; ``snr`` is the peak over the median of the
    profile's other gradients. Returns ``(nan, 0, 0)`` off the photo.
    """
    H, W = gray.shape
    S = np.arange(-half - 2.5, half + 2.5 + 1e-9, 0.25)
    xs, ys = p[0] + S * u[0], p[1] + S * u[1]
    if xs.min() < 1 or xs.max() > W - 2 or ys.min() < 1 or ys.max() > H - 2:
        return np.nan, 0.0, 0.0
    prof = _sample(gray, xs[None], ys[None])[0]
    ker = np.exp(-0.5 * (np.arange(-9, 10) / 3.0) ** 2)
    sm = np.convolve(prof, ker / ker.sum(), mode="same")
    g = np.abs(np.gradient(sm)) * 4.0            # intensity per pixel
    inner = (S >= -half) & (S <= half)
    idx = np.nonzero(inner)[0]
    j = int(idx[np.argmax(g[idx])])
    pos = _subpixel_peak(g, j)
    # contrast of the peak over the profile's other gradients (texture), 1 px around it excluded
    rest = np.r_[g[:max(0, j - 4)], g[j + 5:]]
    snr = float(g[j] / (np.median(rest) + 0.5)) if len(rest) else 0.0
    return float(np.interp(pos, np.arange(len(S)), S)), float(g[j]), snr


def _interior_colour(rgb_f: np.ndarray, p: np.ndarray, u: np.ndarray, half: float) -> np.ndarray:
    """(4,) mean chromaticity (r, g, b) and intensity of the segment ``p + s u, |s| <= half``
    of the (H, W, 3) float32 photo ``rgb_f``."""
    S = np.linspace(-half, half, 9)
    xs, ys = p[0] + S * u[0], p[1] + S * u[1]
    v = _sample(rgb_f, xs[None], ys[None])[0]        # (9, 3)
    tot = v.sum(1, keepdims=True) + 30.0
    return np.r_[(v / tot).mean(0), v.mean() / 255.0]


def track_stem_base(gray: np.ndarray, edges: TrunkEdges, ground_mask: np.ndarray, tree_mask: np.ndarray,
                    *, rgb: np.ndarray | None = None, rope_half_px: float = 1.5, min_rel_gradient: float = 0.35,
                    max_miss_frac: float = 0.4, max_colour_z: float = 4.0, min_snr: float = 3.0) -> tuple[np.ndarray | None, str, dict]:
    """Follow the stem's two silhouette edges down from the rope to where they end.

    The edges found at the rope are tracked step by step down the stem (each side searched
    near its straight-line prediction from the points tracked so far); where both stop, the stem
    meets the ground - or something hides it. What lies just below tells which: ground pixels
    (``ground_mask``) give the base; the stem's own mask, vegetation or another object mean the
    base is hidden or the tracking stopped early, and no base is reported.

    Parameters
    ----------
    gray : (H, W) float32 photo intensity (0-255).
    edges : :class:`TrunkEdges` at the rope (``left_xy``, ``right_xy``, ``along`` pointing down).
    ground_mask, tree_mask : (H, W) bool segmenter ground pixels / the roped stem's mask.
    rope_half_px : half thickness of the rope band (the tracking starts below its bulge).
    min_rel_gradient, min_snr : an edge point counts when its gradient is at least this
        fraction of that side's gradient near the rope, or at least ``min_snr`` times the
        typical gradient along the search line (the background behind the stem changes).
    max_miss_frac : tracking stops after a gap of this fraction of the stem width (both sides
        lost) and the base is the last step where both were found.
    rgb : (H, W, 3) uint8 photo, optional: the stem's interior colour (between the tracked edges)
        must stay like its colour below the rope; where it changes (grass or litter in front of
        the stem: edges of grass blades would otherwise be followed down), the tracking stops.
    max_colour_z : ... by more than this many standard deviations of the colour near the rope.

    Returns
    -------
    (base_xy, status, info): ``base_xy`` (2,) image pixel at the bottom of the stem's mid-line
    or None; ``status`` "ground", "occluded", "edge" (ran out of the photo) or "lost";
    ``info`` holds the tracked points (``left``, ``right``: (N, 2)) and the stem width there.
    """
    H, W = gray.shape
    a = np.asarray(edges.along, np.float64)
    a = a / np.linalg.norm(a)
    u = np.array([a[1], -a[0]]) if (edges.right_xy - edges.left_xy) @ np.array([a[1], -a[0]]) > 0 \
        else np.array([-a[1], a[0]])
    c = 0.5 * (edges.left_xy + edges.right_xy)
    w0 = float(edges.width_px)
    hist = {"L": [(0.0, -w0 / 2)], "R": [(0.0, w0 / 2)]}
    g_first: dict = {"L": [], "R": []}      # gradients of the first points: the side's reference
    dt = max(1.5, 0.08 * w0)
    t = 3.0 * rope_half_px + 3.0
    t_both = None
    gap = 0.0
    status = "lost"
    cols: list = []          # interior colour of the first tracked steps (the reference)
    col_bad = 0
    info: dict = {}
    rgb_f = None if rgb is None else rgb.astype(np.float32)     # once: sampled at every step

    def predict(side, t_):
        h = np.array(hist[side][-10:])
        if len(h) >= 3:
            coef = np.linalg.lstsq(np.c_[np.ones(len(h)), h[:, 0]], h[:, 1], rcond=None)[0]
            return float(coef[0] + coef[1] * t_)
        return float(h[-1, 1])

    def edge_at(side, t_, s_pred):
        """The side's edge near its prediction ``s_pred`` at ``t_``: ``(s, gradient)`` if strong
        enough, False if too weak, None off the photo."""
        p = c + t_ * a + s_pred * u
        s_off, g, snr = _peak_near(gray, p, u, max(2.0, 0.08 * w0))
        if not np.isfinite(s_off):
            return None
        ref = np.median(g_first[side]) if g_first[side] else g
        if g >= 2.0 and (g >= min_rel_gradient * ref or snr >= min_snr):
            return s_pred + s_off, g
        return False

    half_run = 0.0          # length tracked on one side only (the other hidden or low-contrast)
    while True:
        pred = {side: predict(side, t) for side in ("L", "R")}
        pts = {}
        for side in ("L", "R"):
            p = c + t * a + pred[side] * u
            if not (2 <= p[0] < W - 3 and 2 <= p[1] < H - 3):
                status = "edge"
                break
            e = edge_at(side, t, pred[side])
            if e is None:
                status = "edge"
                break
            if e:
                pts[side] = e[0]
                if len(g_first[side]) < 5:
                    g_first[side].append(e[1])
        if status == "edge":
            break
        full = {**pred, **pts}
        ok = bool(pts) and 0.7 * w0 < full["R"] - full["L"] < 1.9 * w0
        if ok and len(pts) == 1:
            half_run += dt
            ok = half_run <= 1.5 * w0
        elif ok:
            half_run = 0.0
        if ok and rgb_f is not None:
            mid = c + t * a + 0.5 * (full["L"] + full["R"]) * u
            col = _interior_colour(rgb_f, mid, u, 0.25 * (full["R"] - full["L"]))
            if len(cols) < 8:
                cols.append(col)
            else:
                ref = np.array(cols)
                z = np.abs(col - ref.mean(0)) / np.maximum(ref.std(0), [0.01, 0.01, 0.01, 0.03])
                if z.max() > max_colour_z:
                    col_bad += 1
                    ok = False
                    if col_bad >= 2:
                        info["stop"] = "colour"
                        break
                else:
                    col_bad = 0
        if ok:
            for side in pts:
                hist[side].append((t, pts[side]))
            t_both = t
            gap = 0.0
        else:
            gap += dt
            if gap > max_miss_frac * w0 + 2 * dt:
                info["stop"] = "gap:" + "".join(sorted(pts))
                break
        t += dt
        if t > 4 * max(H, W):
            break
    info.update(left=np.array([c + tt * a + s * u for tt, s in hist["L"]]),
                right=np.array([c + tt * a + s * u for tt, s in hist["R"]]))
    if t_both is None:
        return None, status if status == "edge" else "lost", info
    # the end to a pixel: finer steps past the last step where the edges were found
    for t_f in np.arange(t_both + 0.5, t_both + 2 * dt, 0.5):
        if not all(edge_at(side, t_f, predict(side, t_f)) for side in ("L", "R")):
            break
        t_both = float(t_f)
    sl, sr = predict("L", t_both), predict("R", t_both)
    width = sr - sl
    base = c + t_both * a + 0.5 * (sl + sr) * u
    info["width_px"] = float(width)
    info["end_xy"] = base
    if status == "edge" or t_both < 1.5 * w0:
        return None, status if status == "edge" else "lost", info
    def grid(t0, t1, half_frac):
        """Pixels (x, y) of a 6 x 5 grid: ``t0..t1`` along the stem, +-half_frac x width across."""
        tt = np.linspace(t0, t1, 6)
        ss = np.linspace(0.5 * (sl + sr) - half_frac * width, 0.5 * (sl + sr) + half_frac * width, 5)
        P = c[None, None] + tt[:, None, None] * a + ss[None, :, None] * u
        return np.round(P[..., 0]).astype(int).ravel(), np.round(P[..., 1]).astype(int).ravel()

    # the stem's last stretch must still be on the (coarse) tree mask: tracked edges that ran on
    # into the ground (shadows, litter as dark as the bark) end well below where the mask does
    xi, yi = grid(max(0.0, t_both - 0.6 * width), t_both, 0.3)
    info["end_on_mask"] = float(tree_mask[np.clip(yi, 0, H - 1), np.clip(xi, 0, W - 1)].mean())
    if info["end_on_mask"] < 0.25:
        return None, "off_mask", info
    # what lies just below the stem's end, across its middle half
    xi, yi = grid(t_both + 0.15 * width + 2, t_both + 0.6 * width + 3, 0.25)
    inside = (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
    if inside.mean() < 0.8:
        return None, "edge", info
    gr = ground_mask[yi[inside], xi[inside]].mean()
    tr = tree_mask[yi[inside], xi[inside]].mean()
    info["below_ground_tree"] = (float(gr), float(tr))
    if gr >= 0.6 and tr <= 0.3:
        return base, "ground", info
    return None, "occluded", info
