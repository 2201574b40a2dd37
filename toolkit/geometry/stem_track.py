"""The edge tracker: the stem's two silhouette edges followed down from the rope to where they end.

Imported by :mod:`.stem_base` (the stem base when neither the user nor the stem-base network gives
one); imports numpy and :mod:`.edges`. The edges found at the rope are tracked step by step down
the stem (each side searched near its straight-line prediction from the points tracked so far);
where both stop, the stem meets the ground - or something hides it. What lies just below tells
which.
"""
from __future__ import annotations

import numpy as np

from .config import StemBaseConfig
from .edges import SMOOTH_KERNEL, TrunkEdges, sample_image, subpixel_peak

__all__ = ["track_stem_base"]


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
    prof = sample_image(gray, xs[None], ys[None])[0]
    sm = np.convolve(prof, SMOOTH_KERNEL, mode="same")
    g = np.abs(np.gradient(sm)) * 4.0            # intensity per pixel
    inner = (S >= -half) & (S <= half)
    idx = np.nonzero(inner)[0]
    j = int(idx[np.argmax(g[idx])])
    pos = subpixel_peak(g, j)
    # contrast of the peak over the profile's other gradients (texture), 1 px around it excluded
    rest = np.r_[g[:max(0, j - 4)], g[j + 5:]]
    snr = float(g[j] / (np.median(rest) + 0.5)) if len(rest) else 0.0
    return float(np.interp(pos, np.arange(len(S)), S)), float(g[j]), snr


def _interior_colour(rgb_f: np.ndarray, p: np.ndarray, u: np.ndarray, half: float) -> np.ndarray:
    """(4,) mean chromaticity (r, g, b) and intensity of the segment ``p + s u, |s| <= half``
    of the (H, W, 3) float32 photo ``rgb_f``."""
    S = np.linspace(-half, half, 9)
    xs, ys = p[0] + S * u[0], p[1] + S * u[1]
    v = sample_image(rgb_f, xs[None], ys[None])[0]        # (9, 3)
    tot = v.sum(1, keepdims=True) + 30.0
    return np.r_[(v / tot).mean(0), v.mean() / 255.0]


class _Track:
    """The two sides tracked so far: positions ``s`` across the stem (pixels from the rope's
    mid-point ``c`` along ``u``) at distances ``t`` down it (along ``a``)."""

    def __init__(self, gray: np.ndarray, edges: TrunkEdges, cfg: StemBaseConfig):
        a = np.asarray(edges.along, np.float64)
        a = a / np.linalg.norm(a)
        u = np.array([a[1], -a[0]]) if (edges.right_xy - edges.left_xy) @ np.array([a[1], -a[0]]) > 0 \
            else np.array([-a[1], a[0]])
        self.gray, self.a, self.u, self.cfg = gray, a, u, cfg
        self.c = 0.5 * (edges.left_xy + edges.right_xy)
        self.w0 = w0 = float(edges.width_px)
        self.hist = {"L": [(0.0, -w0 / 2)], "R": [(0.0, w0 / 2)]}
        self.g_first: dict = {"L": [], "R": []}      # gradients of the first points: the side's reference

    def point(self, t_: float, s_: float) -> np.ndarray:
        """(2,) image pixel at ``t_`` down the stem and ``s_`` across it."""
        return self.c + t_ * self.a + s_ * self.u

    def predict(self, side: str, t_: float) -> float:
        """The side's position at ``t_``: a straight line through its last 10 tracked points."""
        h = np.array(self.hist[side][-10:])
        if len(h) >= 3:
            coef = np.linalg.lstsq(np.c_[np.ones(len(h)), h[:, 0]], h[:, 1], rcond=None)[0]
            return float(coef[0] + coef[1] * t_)
        return float(h[-1, 1])

    def edge_at(self, side: str, t_: float, s_pred: float):
        """The side's edge near its prediction ``s_pred`` at ``t_``: ``(s, gradient)`` if strong
        enough, False if too weak, None off the photo."""
        s_off, g, snr = _peak_near(self.gray, self.point(t_, s_pred), self.u, max(2.0, 0.08 * self.w0))
        if not np.isfinite(s_off):
            return None
        ref = np.median(self.g_first[side]) if self.g_first[side] else g
        if g >= 2.0 and (g >= self.cfg.min_rel_gradient * ref or snr >= self.cfg.min_snr):
            return s_pred + s_off, g
        return False

    def step(self, t: float, pred: dict):
        """Both sides' edges at ``t`` near their predictions ``pred``: {side: s} of those found,
        or None where a side leaves the photo."""
        H, W = self.gray.shape
        pts = {}
        for side in ("L", "R"):
            p = self.point(t, pred[side])
            if not (2 <= p[0] < W - 3 and 2 <= p[1] < H - 3):
                return None
            e = self.edge_at(side, t, pred[side])
            if e is None:
                return None
            if e:
                pts[side] = e[0]
                if len(self.g_first[side]) < 5:
                    self.g_first[side].append(e[1])
        return pts


class _ColourCheck:
    """The stem's interior colour against its first 8 tracked steps (the reference)."""

    def __init__(self, max_colour_z: float):
        self.cols: list = []
        self.bad = 0
        self.max_colour_z = max_colour_z

    def __call__(self, col: np.ndarray) -> tuple[bool, bool]:
        """``(ok, stop)`` for the (4,) colour ``col`` of the next step: not ok where it departs
        from the reference; stop at the second such step in a row."""
        if len(self.cols) < 8:
            self.cols.append(col)
            return True, False
        ref = np.array(self.cols)
        z = np.abs(col - ref.mean(0)) / np.maximum(ref.std(0), [0.01, 0.01, 0.01, 0.03])
        if z.max() > self.max_colour_z:
            self.bad += 1
            return False, self.bad >= 2
        self.bad = 0
        return True, False


def _follow(tr: _Track, rgb_f: np.ndarray | None, t: float, dt: float, info: dict) -> tuple[float | None, str]:
    """Track both sides down from ``t`` in steps ``dt``: ``(t_both, status)``, the last ``t``
    where both were found (None if never) and "edge" (ran out of the photo) or "lost"; why the
    tracking stopped goes to ``info["stop"]``."""
    H, W = tr.gray.shape
    w0, t_both, gap, half_run = tr.w0, None, 0.0, 0.0     # half_run: tracked on one side only
    colour = _ColourCheck(tr.cfg.max_colour_z)
    while True:
        pred = {side: tr.predict(side, t) for side in ("L", "R")}
        pts = tr.step(t, pred)
        if pts is None:
            return t_both, "edge"
        full = {**pred, **pts}
        ok = bool(pts) and 0.7 * w0 < full["R"] - full["L"] < 1.9 * w0
        if ok and len(pts) == 1:
            half_run += dt
            ok = half_run <= 1.5 * w0
        elif ok:
            half_run = 0.0
        if ok and rgb_f is not None:
            mid = tr.point(t, 0.5 * (full["L"] + full["R"]))
            ok, stop = colour(_interior_colour(rgb_f, mid, tr.u, 0.25 * (full["R"] - full["L"])))
            if stop:
                info["stop"] = "colour"
                return t_both, "lost"
        if ok:
            for side in pts:
                tr.hist[side].append((t, pts[side]))
            t_both = t
            gap = 0.0
        else:
            gap += dt
            if gap > tr.cfg.max_miss_frac * w0 + 2 * dt:
                info["stop"] = "gap:" + "".join(sorted(pts))
                return t_both, "lost"
        t += dt
        if t > 4 * max(H, W):
            return t_both, "lost"


def _end_status(tr: _Track, t_both: float, sl: float, sr: float, ground_mask: np.ndarray,
                tree_mask: np.ndarray, info: dict) -> str:
    """What the tracked stem's end at ``t_both`` (sides ``sl``, ``sr``) is: "ground" (ground
    pixels below it), "off_mask" (the edges ran on past the tree mask), "edge" (what lies below
    is outside the photo) or "occluded"."""
    H, W = tree_mask.shape
    width = sr - sl

    def grid(t0, t1, half_frac):
        """Pixels (x, y) of a 6 x 5 grid: ``t0..t1`` along the stem, +-half_frac x width across."""
        tt = np.linspace(t0, t1, 6)
        ss = np.linspace(0.5 * (sl + sr) - half_frac * width, 0.5 * (sl + sr) + half_frac * width, 5)
        P = tr.c[None, None] + tt[:, None, None] * tr.a + ss[None, :, None] * tr.u
        return np.round(P[..., 0]).astype(int).ravel(), np.round(P[..., 1]).astype(int).ravel()

    # the stem's last stretch must still be on the (coarse) tree mask: tracked edges that ran on
    # into the ground (shadows, litter as dark as the bark) end well below where the mask does
    xi, yi = grid(max(0.0, t_both - 0.6 * width), t_both, 0.3)
    info["end_on_mask"] = float(tree_mask[np.clip(yi, 0, H - 1), np.clip(xi, 0, W - 1)].mean())
    if info["end_on_mask"] < 0.25:
        return "off_mask"
    # what lies just below the stem's end, across its middle half
    xi, yi = grid(t_both + 0.15 * width + 2, t_both + 0.6 * width + 3, 0.25)
    inside = (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
    if inside.mean() < 0.8:
        return "edge"
    gr = ground_mask[yi[inside], xi[inside]].mean()
    tr_ = tree_mask[yi[inside], xi[inside]].mean()
    info["below_ground_tree"] = (float(gr), float(tr_))
    return "ground" if gr >= 0.6 and tr_ <= 0.3 else "occluded"


def track_stem_base(gray: np.ndarray, edges: TrunkEdges, ground_mask: np.ndarray, tree_mask: np.ndarray,
                    *, rgb: np.ndarray | None = None, rope_half_px: float = 1.5,
                    config: StemBaseConfig | None = None) -> tuple[np.ndarray | None, str, dict]:
    """Follow the stem's two silhouette edges down from the rope to where they end.

    Where both edges stop, ground pixels just below (``ground_mask``) give the base; the stem's
    own mask, vegetation or another object mean the base is hidden or the tracking stopped
    early, and no base is reported.

    Parameters
    ----------
    gray : (H, W) float32 photo intensity (0-255).
    edges : :class:`~.edges.TrunkEdges` at the rope (``left_xy``, ``right_xy``, ``along`` pointing down).
    ground_mask, tree_mask : (H, W) bool segmenter ground pixels / the roped stem's mask.
    rgb : (H, W, 3) uint8 photo, optional: the stem's interior colour (between the tracked edges)
        must stay like its colour below the rope; where it changes (grass or litter in front of
        the stem: edges of grass blades would otherwise be followed down), the tracking stops.
    rope_half_px : half thickness of the rope band (the tracking starts below its bulge).
    config : :class:`~.config.StemBaseConfig` (default when None): the gradient, gap and colour
        thresholds of the tracking.

    Returns
    -------
    (base_xy, status, info): ``base_xy`` (2,) image pixel at the bottom of the stem's mid-line
    or None; ``status`` "ground", "occluded", "off_mask", "edge" (ran out of the photo) or
    "lost"; ``info`` holds the tracked points (``left``, ``right``: (N, 2)), and where the
    tracking got far enough the stem width there and its lowest point (``end_xy``).
    """
    tr = _Track(gray, edges, config or StemBaseConfig())
    dt = max(1.5, 0.08 * tr.w0)
    info: dict = {}
    rgb_f = None if rgb is None else rgb.astype(np.float32)     # once: sampled at every step
    t_both, status = _follow(tr, rgb_f, 3.0 * rope_half_px + 3.0, dt, info)
    info.update(left=np.array([tr.point(tt, s) for tt, s in tr.hist["L"]]),
                right=np.array([tr.point(tt, s) for tt, s in tr.hist["R"]]))
    if t_both is None:
        return None, status, info
    # the end to a pixel: finer steps past the last step where the edges were found
    for t_f in np.arange(t_both + 0.5, t_both + 2 * dt, 0.5):
        if not all(tr.edge_at(side, t_f, tr.predict(side, t_f)) for side in ("L", "R")):
            break
        t_both = float(t_f)
    sl, sr = tr.predict("L", t_both), tr.predict("R", t_both)
    base = tr.point(t_both, 0.5 * (sl + sr))
    info["width_px"] = float(sr - sl)
    info["end_xy"] = base
    if status == "edge" or t_both < 1.5 * tr.w0:
        return None, status, info
    status = _end_status(tr, t_both, sl, sr, ground_mask, tree_mask, info)
    return (base if status == "ground" else None), status, info
