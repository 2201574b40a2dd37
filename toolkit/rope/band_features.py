"""The band detector's candidate features (the band and its surroundings) and its log-odds
score; imported by :mod:`.band` and by the score-weight fitter.

The score (log-odds, :attr:`~.config.BandConfig.score_weights`, fitted on synthetic photos plus
rope-free real photos; see :func:`candidate_features`) weighs: contrast, redness, length,
continuity, thinness, red (not orange) hue, fit residual, red clutter and red area around the
band, evenness along it, whether both band ends sit on a vertical intensity edge (the trunk
silhouette) that holds above and below the band, and whether the surface above the band matches
the one below (one trunk face, not a horizon between two trunks). Hard gates: length >=
``min_elongation`` x thickness, hue ``(G - B) / R <= max_hue``.

Each context pass (:func:`band_clutter`, :func:`trunk_edges`, :func:`surface_continuity`,
:func:`red_area`, :func:`peakiness`) is a pure function of a :class:`~.band_segments.BandFit`
(working-image pixels) and the maps of :class:`ContextMaps`; :func:`band_context` gathers them.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from .band_segments import BandFit
from .config import BandConfig
from .score import linear_score

__all__ = ["BoxCounts", "ContextMaps", "BandContext", "context_maps", "band_context", "band_clutter",
           "trunk_edges", "surface_continuity", "red_area", "peakiness", "candidate_features", "candidate_score"]


class BoxCounts:
    """Box counts of a binary map on a grid of ``cell`` x ``cell`` pixels (integral image).

    Parameters
    ----------
    mask : (H, W) bool or 0/1.
    cell : grid cell, pixels.
    """

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


@dataclass(frozen=True)
class ContextMaps:
    """The working image's maps the context passes read.

    Attributes
    ----------
    counts : :class:`BoxCounts` of the level-0 piece pixels.
    gray_ii, rb_ii : (H + 1, W + 1) int32 integral images of grey and ``(R - B) / 2 + 128``.
    redness : (H, W) float32 level-0 red-ness.
    contrasts : the thin-line contrast of each pyramid level.
    """
    counts: BoxCounts
    gray_ii: np.ndarray
    rb_ii: np.ndarray
    redness: np.ndarray
    contrasts: list


@dataclass(frozen=True)
class BandContext:
    """What surrounds a band (the candidate features beyond the band itself).

    Attributes
    ----------
    clutter, density : red line pixels around the band (:func:`band_clutter`).
    edges, edge_snr : trunk silhouette at the band ends (:func:`trunk_edges`).
    step, corr : the surface above against the one below (:func:`surface_continuity`).
    red_area : red surroundings (:func:`red_area`); peaky : unevenness along it (:func:`peakiness`).
    """
    clutter: float
    density: float
    edges: tuple
    edge_snr: float
    step: float
    corr: float
    red_area: float
    peaky: float


def context_maps(small: np.ndarray, counts: BoxCounts, redness: np.ndarray, contrasts: list) -> ContextMaps:
    """The context maps of the working image ``small`` ((H, W, 3) uint8)."""
    gray_ii = cv2.integral(cv2.cvtColor(small, cv2.COLOR_RGB2GRAY), sdepth=cv2.CV_32S)
    rb = cv2.addWeighted(small[..., 0], 0.5, small[..., 2], -0.5, 128.0)       # (R - B) / 2 + 128, uint8
    rb_ii = cv2.integral(rb, sdepth=cv2.CV_32S)
    return ContextMaps(counts, gray_ii, rb_ii, redness, contrasts)


def band_context(fit: BandFit, maps: ContextMaps, config: BandConfig | None = None) -> BandContext:
    """All context passes of one band."""
    cfg = BandConfig() if config is None else config
    clutter, density = band_clutter(fit, maps.counts)
    edges, edge_snr = trunk_edges(fit, maps.gray_ii, cfg.edge_strip, cfg.edge_strips)
    step, corr = surface_continuity(fit, [maps.gray_ii, maps.rb_ii])
    return BandContext(clutter=clutter, density=density, edges=edges, edge_snr=edge_snr, step=step, corr=corr,
                       red_area=red_area(fit, maps.redness), peaky=peakiness(fit, maps.contrasts))


def band_clutter(fit: BandFit, counts: BoxCounts) -> tuple[float, float]:
    """Thin red lines around a band (level-0 pixels): ``(clutter, density)``.

    ``clutter``: line pixels on the trunk face just above and below the band (within its x range),
    relative to the band's area; ``density``: fraction of line pixels in a box around the band.
    """
    p, L, T = fit.polyline, fit.length_px, max(fit.thickness_px, 1.0)
    x0, x1 = p[0, 0] + 0.1 * L, p[-1, 0] - 0.1 * L
    ya, yb = p[:, 1].min(), p[:, 1].max()
    face = counts(x0, ya - 0.5 * L, x1, yb + 0.5 * L)
    band = counts(x0, ya - T - 2, x1, yb + T + 2)
    clutter = max(0.0, face - band) / max(L * T, 1.0)
    m = max(16.0, 0.6 * L)
    box = (p[0, 0] - m, ya - m, p[-1, 0] + m, yb + m)
    return clutter, counts(*box) / max(counts.area(*box), 1.0)


def _maxfilt(v: np.ndarray, r: int) -> np.ndarray:
    """Running maximum along the rows of a (K, N) float32 array over windows of half width ``r``."""
    if r <= 0:
        return v
    return cv2.dilate(v, _line_kernel(r), borderType=cv2.BORDER_REPLICATE)


@functools.lru_cache(maxsize=256)
def _line_kernel(r: int) -> np.ndarray:
    return np.ones((1, 2 * r + 1), np.uint8)


def trunk_edges(fit: BandFit, gray_integral: np.ndarray, strip: float, nstrip: int) -> tuple[tuple, float]:
    """Do both band ends sit on a vertical intensity edge (the trunk silhouette)?

    For each end, the grey column means of horizontal strips (``nstrip`` above and below the
    band, each ``strip`` times the band length high) are taken in a window around the end; a step
    between the means of two adjacent boxes must appear in every strip with the same sign,
    allowing for a trunk leaning up to 15 deg.

    Returns
    -------
    (edges, edge_snr) : ``edges`` = per end ``step / (step + 6)`` (grey levels); ``edge_snr`` =
    geometric mean over the ends of the step over the median step in the window (a lone
    silhouette vs foliage texture).
    """
    L = fit.length_px
    T = max(fit.thickness_px, 1.0)
    hs = int(min(max(strip * L, 4), 160))          # height of each sub-strip
    a = int(min(max(0.05 * L, 1), 16))             # width of the step boxes
    s = int(min(max(0.2 * L, 3), 100))             # search range around the band end
    out, snr = [], []
    for (xe, ye) in (fit.polyline[0], fit.polyline[-1]):
        e, r = _end_step(gray_integral, xe, ye, T, hs, a, s, nstrip)
        out.append(e)
        snr.append(r)
    return (out[0], out[1]), (float(np.sqrt(snr[0] * snr[1])) if len(snr) == 2 else 0.0)


def _end_step(II: np.ndarray, xe, ye, T: float, hs: int, a: int, s: int, nstrip: int) -> tuple[float, float]:
    """``(step / (step + 6), step / (median step + 2))`` of the edge at one band end (0, 0 when
    the strips leave the image)."""
    H, W = II.shape[0] - 1, II.shape[1] - 1
    xa = int(round(xe)) - s - a - 1
    xb = int(round(xe)) + s + a + 2
    prof, reach = [], []
    if xa >= 0 and xb <= W:
        for k in range(-nstrip, nstrip):
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
        return 0.0, 0.0
    P = np.stack(prof).astype(np.float32)
    D = (P[:, 2 * a:] - 2 * P[:, a:-a] + P[:, :-2 * a]) / a    # right box mean - left box mean
    if D.shape[1] == 0:
        return 0.0, 0.0
    # both step signs at once; strips with the same lean allowance dilated together
    DD = np.concatenate([D, -D])
    rr = np.array(reach + reach)
    M = np.empty_like(DD)
    for r in np.unique(rr):
        M[rr == r] = _maxfilt(DD[rr == r], int(r))
    n = len(D)
    best = max(0.0, float(M[:n].min(0).max()), float(M[n:].min(0).max()))
    return best / (best + 6.0), best / (float(np.median(np.abs(D))) + 2.0)


def surface_continuity(fit: BandFit, iis: list[np.ndarray]) -> tuple[float, float]:
    """Is the surface just above the band the same as just below it (one trunk face)?

    Mean column profiles (grey, and red minus blue) of a strip above and a strip below the band,
    within its x range, are compared. A rope on a trunk has the same bark, lit the same way
    (similar means, correlated profiles); a horizon or a ground edge running between two trunks
    has sky or far trees above and ground below.

    Returns
    -------
    (step, corr) : largest relative difference of means; correlation of the grey profiles (0
    when too few columns). ``(0.5, 0.0)`` when the strips leave the image.
    """
    L = fit.length_px
    T = max(fit.thickness_px, 1.0)
    p = fit.polyline
    H, W = iis[0].shape[0] - 1, iis[0].shape[1] - 1
    x0 = int(round(p[0, 0] + 0.15 * L))
    x1 = int(round(p[-1, 0] - 0.15 * L))
    hs = int(min(max(0.25 * L, 3), 60))
    inner = p[(p[:, 0] >= x0) & (p[:, 0] <= x1), 1]
    if x1 - x0 < 3 or len(inner) == 0:
        return 0.5, 0.0
    ya1 = int(round(inner.min() - T - 1))
    yb0 = int(round(inner.max() + T + 1))
    ya0, yb1 = ya1 - hs, yb0 + hs
    if ya0 < 0 or yb1 > H or x0 < 0 or x1 >= W:
        return 0.5, 0.0
    steps, prof = [], []
    for k, II in enumerate(iis):
        a = np.diff(II[ya1, x0:x1 + 2] - II[ya0, x0:x1 + 2]) / hs
        b = np.diff(II[yb1, x0:x1 + 2] - II[yb0, x0:x1 + 2]) / hs
        ma, mb = float(a.mean()), float(b.mean())
        steps.append(abs(ma - mb) / (20.0 + (0.5 * (abs(ma) + abs(mb)) if k == 0 else 0.0)))
        if k == 0:
            prof = (a, b)
    a, b = prof
    sa, sb = a.std(), b.std()
    corr = float(np.mean((a - a.mean()) * (b - b.mean())) / (sa * sb)) if sa > 1.0 and sb > 1.0 else 0.0
    return float(max(steps)), corr


def red_area(fit: BandFit, F: np.ndarray) -> float:
    """Fraction of the surroundings (band excluded) about as red as the band: red leaves, a jacket
    or a blob light up around a "band" found inside them; bark around a rope does not.

    Parameters
    ----------
    F : (H, W) float32 level-0 red-ness.
    """
    H, W = F.shape
    p, L, T = fit.polyline, fit.length_px, max(fit.thickness_px, 1.0)
    x0, x1 = int(max(0, p[0, 0] - 0.3 * L)), int(min(W, p[-1, 0] + 0.3 * L + 1))
    y0, y1 = int(max(0, p[:, 1].min() - 0.5 * L)), int(min(H, p[:, 1].max() + 0.5 * L + 1))
    st = max(1, int(L / 40))
    sub = F[y0:y1:st, x0:x1:st]
    if sub.size == 0:
        return 0.0
    xs = np.arange(x0, x1, st)
    yc = np.interp(xs, p[:, 0], p[:, 1])
    band = np.abs(np.arange(y0, y1, st)[:, None] - yc[None, :]) <= T + 2
    v = sub[~band]
    return float(np.mean(v > 0.5 * fit.red)) if v.size else 0.0


def peakiness(fit: BandFit, Rs: list[np.ndarray]) -> float:
    """How uneven the line contrast is along the band: log(90th percentile / median) of the
    per-column maxima, on the band's pyramid level. A rope is even; a row of red dots (leaves,
    berries) is peaky."""
    lv = min(fit.level, len(Rs) - 1)
    R = Rs[lv]
    f = 2.0 ** lv
    H, W = R.shape
    p = fit.polyline / f
    xs = np.arange(int(np.ceil(p[0, 0])), int(np.floor(p[-1, 0])) + 1)
    xs = xs[(xs >= 0) & (xs < W)]
    if len(xs) < 3:
        return 0.0
    yc = np.interp(xs, p[:, 0], p[:, 1])
    r = int(np.ceil(0.5 * fit.thickness_px / f)) + 1
    rows = np.clip(np.round(yc)[None, :].astype(int) + np.arange(-r, r + 1)[:, None], 0, H - 1)
    v = R[rows, xs[None, :]].max(0)
    q50, q90 = np.percentile(v, [50, 90])
    return float(np.log((q90 + 0.003) / (q50 + 0.003)))


def candidate_features(fit: BandFit, ctx: BandContext) -> dict:
    """Features of a band and its context (working-image pixels) entering its score."""
    T = max(fit.thickness_px, 0.7)
    return dict(
        log_contrast=float(np.log(min(fit.contrast, 0.08))), log_length=float(np.log(fit.length_px)),
        log_density=float(np.log(ctx.density + 0.002)), coverage=float(fit.coverage),
        shape=float(np.clip((fit.length_px / T - 3.0) / 10.0, 0.0, 1.0)), hue=float(max(0.0, fit.hue - 0.15)),
        edge_min=float(min(ctx.edges)), edge_max=float(max(ctx.edges)), log_clutter=float(np.log1p(ctx.clutter)),
        members=float(fit.members - 1), coarse=float(fit.level >= 2), resid=float(fit.resid / T),
        step=float(min(ctx.step, 1.0)), corr=float(ctx.corr), red_area=float(ctx.red_area),
        peaky=float(ctx.peaky), log_red=float(np.log(fit.red + 0.01)), log_edge_snr=float(np.log1p(ctx.edge_snr)))


def candidate_score(fit: BandFit, features: dict, weights: dict, config: BandConfig | None = None) -> float:
    """Log-odds that the band is the rope: ``bias + sum_k w_k * feature_k`` (:func:`.score.linear_score`),
    ``-inf`` for a band too short for its thickness or too orange; ``deep_prior`` lower for a
    band scored beyond the band-score budget."""
    cfg = BandConfig() if config is None else config
    if fit.length_px < cfg.min_elongation * max(fit.thickness_px, 0.7) or fit.hue > cfg.max_hue:
        s = -np.inf
    else:
        s = linear_score(features, weights)
    return s - (cfg.deep_prior if fit.deep else 0.0)
