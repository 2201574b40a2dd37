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

__all__ = ["TrunkEdges", "trunk_edges", "trace_stem_base"]


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
    m8 = tree_mask.astype(np.uint8)
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
    gs = gray.astype(np.float32)
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
            return TrunkEdges(reason="the stem runs out of the photo at the rope (step back or re-frame "
                                     "so that both sides of the stem show)")
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
