"""Sub-pixel silhouette edges of a stem across the rope (:func:`trunk_edges`), and the tools they share.

Imported by the stages of :mod:`monodbh.toolkit.geometry` (:mod:`.stem_edges`, :mod:`.stem_track`,
:mod:`.measure`); imports numpy and cv2. The tree mask (from the segmenter, possibly coarse) says
roughly where the stem's left and right borders are; the photo's gradient along lines parallel
to the rope places them to a fraction of a pixel. Lines are sampled above and below the rope band
(the rope itself bulges the silhouette), and straight lines fitted through the edge points give
the edges at the rope's height.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .config import EdgeConfig

__all__ = ["TrunkEdges", "trunk_edges", "rope_row_contrast", "rope_curve", "band_mask", "combine_edges", "refit_edges",
           "channel_mean", "sample_image", "subpixel_peak", "SMOOTH_KERNEL", "REASON_OUT_OF_PHOTO"]

#: :attr:`TrunkEdges.reason` when a side of the stem lies outside the photo at the rope
REASON_OUT_OF_PHOTO = ("the stem runs out of the photo at the rope (step back or re-frame so that both "
                       "sides of the stem show)")

#: (19,) Gaussian smoothing of an intensity profile sampled every 0.25 px (sigma 3 samples = 0.75 px)
SMOOTH_KERNEL = np.exp(-0.5 * (np.arange(-9, 10) / 3.0) ** 2)
SMOOTH_KERNEL /= SMOOTH_KERNEL.sum()


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


def channel_mean(rgb: np.ndarray) -> np.ndarray:
    """``rgb.astype(float32).mean(2)`` bit for bit, 7x faster: ``((R + G) + B) / 3`` in float32.

    (numpy's mean over a last axis of 3 is a slow strided reduction: 58 -> 8 ms at 1600 px.)

    Parameters
    ----------
    rgb : (H, W, 3) uint8.

    Returns
    -------
    (H, W) float32.

    Examples
    --------
    >>> px = np.array([[[10, 20, 31]]], np.uint8)
    >>> bool(channel_mean(px)[0, 0] == px.astype(np.float32).mean(2)[0, 0])
    True
    """
    s = rgb[..., 0].astype(np.float32)
    s += rgb[..., 1]
    s += rgb[..., 2]
    s /= 3
    return s


def sample_image(img: np.ndarray, xs: np.ndarray, ys: np.ndarray, nearest: bool = False) -> np.ndarray:
    """``img`` (H, W[, C]) at the points ``(xs, ys)`` (any equal shapes, pixels; 0 outside),
    bilinear or nearest (``cv2.remap``)."""
    import cv2
    mx = xs.astype(np.float32)
    my = ys.astype(np.float32)
    return cv2.remap(img, mx, my, cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def subpixel_peak(g: np.ndarray, i: int) -> float:
    """Sub-sample position of the peak of the (N,) profile ``g`` at index ``i`` (parabola
    through its neighbours; ``i`` itself at the ends or where the profile is not concave)."""
    if 0 < i < len(g) - 1:
        a, b, c = g[i - 1], g[i], g[i + 1]
        den = a - 2 * b + c
        if den < 0:
            return i + 0.5 * (a - c) / den
    return float(i)


def _run_around(mk: np.ndarray, i: int) -> tuple[int, int]:
    """First and last index of the run of true values of the (N,) mask ``mk`` through ``i``."""
    lo = i
    while lo > 0 and mk[lo - 1]:
        lo -= 1
    hi = i
    while hi < len(mk) - 1 and mk[hi + 1]:
        hi += 1
    return lo, hi


def _rope_frame(center_xy, across_dir) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(c, u, a)``: the rope centre (2,), the unit direction across the stem (2,) pointing
    right and the one along it (2,) pointing down the photo."""
    c = np.asarray(center_xy, np.float64)
    u = np.asarray(across_dir, np.float64)
    u = u / np.linalg.norm(u)
    if u[0] < 0:
        u = -u
    a = np.array([-u[1], u[0]])                 # along the stem
    if a[1] < 0:
        a = -a                                  # pointing down the photo
    return c, u, a


def _mask_half_width(m8: np.ndarray, c: np.ndarray, u: np.ndarray) -> float | None:
    """Half the width of the (H, W) uint8 mask's run along the rope line through ``c``
    (pixels, at least 2), or None when the rope centre is not on the mask."""
    H, W = m8.shape
    s = np.arange(-min(W, 4000) / 2, min(W, 4000) / 2, 1.0)
    xs, ys = c[0] + s * u[0], c[1] + s * u[1]
    inside = (xs >= 0) & (xs < W - 1) & (ys >= 0) & (ys < H - 1)
    mk = np.zeros(len(s), np.uint8)
    mk[inside] = sample_image(m8, xs[inside][None], ys[inside][None], nearest=True)[0]
    i0 = int(np.argmin(np.abs(s)))
    if not mk[max(0, i0 - 2):i0 + 3].any():
        return None
    lo, hi = _run_around(mk, i0)
    return max(2.0, (s[hi] - s[lo]) / 2)


def _line_offsets(rope_half_px: float, n_lines: int) -> np.ndarray:
    """(n_lines,) offsets of the sampling lines from the rope along the stem (pixels), nearest
    first, alternately above and below and clear of the rope band."""
    step = max(1.0, 2.0 * rope_half_px)
    offs = []
    k = 0
    while len(offs) < n_lines and k < 4 * n_lines:
        t = (1.5 + k * 0.9) * step + 2.0
        offs += [-t, t]
        k += 1
    return np.array(sorted(offs, key=abs)[:n_lines])


def _border_peak(g: np.ndarray, ok: np.ndarray, border: int, w: int, S: np.ndarray):
    """The gradient peak near the mask ``border`` (sample index) of a line's (N,) gradient ``g``,
    weighted by closeness to the border: ``(s, gradient)`` with ``s`` on the line's positions
    ``S`` (N,), or None where the search window leaves the photo (``ok`` (N,) false)."""
    a0, a1 = max(1, border - w), min(len(S) - 2, border + w)
    if a1 <= a0 or not ok[a0 - 1:a1 + 1].all():
        return None
    prior = np.exp(-0.5 * ((np.arange(a0, a1) - border) / (0.5 * w)) ** 2)
    j = a0 + int(np.argmax(g[a0:a1] * prior))
    pos = subpixel_peak(g, j)
    return np.interp(pos, np.arange(len(S)), S), float(g[j])


def _line_borders(gs: np.ndarray, m8: np.ndarray, base: np.ndarray, u: np.ndarray, S: np.ndarray,
                  search_px: float):
    """The stem's two borders on the sampling line ``base + S u``: None when the line is mostly
    off the photo or misses the mask, else ``[left, right]``, each ``(s, gradient)`` or None
    (that side's window leaves the photo). ``gs`` (H, W) float32, ``m8`` (H, W) uint8 mask."""
    H, W = gs.shape
    xs, ys = base[0] + S * u[0], base[1] + S * u[1]
    ok = (xs >= 1) & (xs < W - 2) & (ys >= 1) & (ys < H - 2)
    if ok.mean() < 0.25:
        return None
    # (a wide stem near the photo's border: the line may leave the photo beyond the stem;
    # only the windows around the two borders have to be inside it)
    prof = sample_image(gs, xs[None], ys[None])[0]
    mk = sample_image(m8, xs[None], ys[None], nearest=True)[0].astype(bool) & ok
    j0 = int(np.argmin(np.abs(S)))
    if not mk[max(0, j0 - 8):j0 + 9].any():
        return None
    # mask borders of the run around the centre
    jj = j0 if mk[j0] else (j0 - 8 + int(np.argmax(mk[max(0, j0 - 8):j0 + 9])))
    l_, r_ = _run_around(mk, jj)
    # gradient magnitude (profile smoothed with sigma ~0.75 px = 3 samples)
    g = np.abs(np.gradient(np.convolve(prof, SMOOTH_KERNEL, mode="same")))
    w = int(search_px * 4)
    return [_border_peak(g, ok, border, w, S) for border in (l_ - 2, r_ + 2)]    # mask border at half-sample


def _robust_line(P: np.ndarray):
    """``s = p0 + p1 t`` through the (N, 3) edge points ``(t, s, gradient)``, refitted without the
    points beyond 3.5 MAD: ``(coef (2,), rms, keep (N,) bool)``."""
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


def _edges_from_points(c, u, a, lefts: list, rights: list) -> TrunkEdges:
    """The edges at the rope from the two sides' points ``(t, s, gradient)``: straight lines
    through each side, the stem direction from their mid-line's slope."""
    L = np.array(lefts)
    R = np.array(rights)
    cl, rms_l, kl = _robust_line(L)
    cr, rms_r, kr = _robust_line(R)
    sl, sr = cl[0], cr[0]
    left = c + sl * u
    right = c + sr * u
    mid_slope = 0.5 * (cl[1] + cr[1])
    along = a + mid_slope * u
    along /= np.linalg.norm(along)
    return TrunkEdges(left_xy=left, right_xy=right, width_px=float(sr - sl), along=along, across=u,
                      edge_rms_px=float(max(rms_l, rms_r)), n_lines=int(min(kl.sum(), kr.sum())),
                      points=dict(left=np.array([c + t * a + s_ * u for t, s_, _ in L[kl]]),
                                  right=np.array([c + t * a + s_ * u for t, s_, _ in R[kr]])))


def trunk_edges(gray: np.ndarray, tree_mask: np.ndarray, center_xy, across_dir, *,
                rope_half_px: float = 1.5, search_px: float = 3.0, config: EdgeConfig | None = None) -> TrunkEdges:
    """Find the stem's silhouette edges at the rope.

    Parameters
    ----------
    gray : (H, W) float32 photo intensity (any scale).
    tree_mask : (H, W) bool mask of the roped tree (same size).
    center_xy : (2,) rope centre on the stem (pixels).
    across_dir : (2,) direction of the rope band across the stem.
    rope_half_px : half thickness of the rope (pixels); lines avoid ``3 x`` that band.
    search_px : how far (pixels) around the mask border the gradient peak is searched.
    config : :class:`~.config.EdgeConfig` (default when None): the number of sampling lines.

    Returns
    -------
    TrunkEdges
    """
    cfg = config or EdgeConfig()
    c, u, a = _rope_frame(center_xy, across_dir)
    tm_ = np.asarray(tree_mask)
    m8 = tm_.view(np.uint8) if tm_.dtype == bool else tm_.astype(np.uint8)      # (no copy of a bool mask)
    half = _mask_half_width(m8, c, u)
    if half is None:
        return TrunkEdges(reason="rope centre is not on the tree mask")
    lefts, rights = [], []
    n_out = 0       # stem borders that fall outside the photo
    S = np.arange(-half * 1.6 - search_px - 3, half * 1.6 + search_px + 3, 0.25)
    gs = np.asarray(gray, np.float32)        # (no copy when it is float32 already)
    for t in _line_offsets(rope_half_px, cfg.n_lines):
        sides = _line_borders(gs, m8, c + t * a, u, S, search_px)
        if sides is None:
            continue
        for found, store in zip(sides, (lefts, rights)):
            if found is None:
                n_out += 1      # the stem runs out of the photo on this side
            else:
                store.append((t, found[0], found[1]))
    if len(lefts) < 3 or len(rights) < 3:
        if n_out >= 3:
            return TrunkEdges(reason=REASON_OUT_OF_PHOTO)
        return TrunkEdges(reason="stem edges not found around the rope")
    return _edges_from_points(c, u, a, lefts, rights)


def rope_row_contrast(redness: np.ndarray, center_xy, rope_dir, across, along, s: np.ndarray, *,
                      rope_half_px: float, sag_px: float = 0.0, curve=None) -> np.ndarray:
    """Red-ness of the rope's row minus that of the rows beside it, at positions across the stem.

    The rope's centre line is the straight line through ``center_xy`` along ``rope_dir``, or the
    ``curve`` where given (a rope seen from above or below is an arc); the position ``s`` is
    measured along ``across`` (the direction of the stem's cross-section).
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
        above or below is an arc), or from ``curve`` where given.
    curve : (5,) ``(c0, c1, c2, s_lo, s_hi)`` from :func:`rope_curve`: the rope's centre line
        as an offset ``t = c0 + c1 s + c2 s^2`` (pixels) normal to ``across`` for ``s`` in
        ``[s_lo, s_hi]``, on along the end's tangent past them; or None: the straight line along
        ``rope_dir``.

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
    if curve is None:
        base = np.asarray(center_xy, np.float64)[None] + (s / max(float(d @ u), 0.3))[:, None] * d[None]
    else:
        sc = np.clip(s, curve[3], curve[4])     # past the line's ends: on along the end's tangent
        t0 = curve[0] + curve[1] * sc + curve[2] * sc * sc + (curve[1] + 2 * curve[2] * sc) * (s - sc)
        base = np.asarray(center_xy, np.float64)[None] + s[:, None] * u[None] + t0[:, None] * _normal_toward(u, a)[None]
    h = max(0.5, float(rope_half_px))
    reach = 1.5 * h + 1.0 + sag_px
    t_in = np.arange(-reach, reach + 1e-6, 0.5)
    t_ref = np.arange(3 * h + 2 + sag_px, 6 * h + 4 + sag_px, 1.0)
    t_ref = np.r_[-t_ref, t_ref]

    def rows(ts):
        P = base[:, None, :] + ts[None, :, None] * a[None, None, :]
        return sample_image(redness, P[..., 0], P[..., 1])

    return (rows(t_in).max(1) - np.median(rows(t_ref), 1)).astype(np.float32)


def _normal_toward(u: np.ndarray, a: np.ndarray) -> np.ndarray:
    """(2,) the unit normal to ``u`` on ``a``'s side (``a`` need not be normal to ``u``)."""
    n = np.array([-u[1], u[0]], np.float64)
    return n if n @ a >= 0 else -n


def rope_curve(polyline, center_xy, across, along) -> np.ndarray | None:
    """The rope's centre line as a quadratic offset along the stem, for :func:`rope_row_contrast`.

    A rope seen from above or below is an arc whose ends rise (or sink) fastest at the stem's
    flanks; a row read along its chord misses it there. The quadratic follows the arc over the
    line and extends it past the line's ends.

    Parameters
    ----------
    polyline : (N, 2) rope centre line (pixels), N >= 3.
    center_xy : (2,) rope centre; across, along : (2,) unit directions across and along the stem.

    Returns
    -------
    (5,) ``(c0, c1, c2, s_lo, s_hi)``: ``t = c0 + c1 s + c2 s^2`` fitted over the line's
    extent ``[s_lo, s_hi]`` (``s``: pixels along ``across`` from ``center_xy``; ``t``: pixels
    normal to it, toward ``along``), or None for fewer than 3 points or a line shorter than 4 px.

    Examples
    --------
    >>> s = np.linspace(-50, 50, 11)
    >>> pl = np.c_[100 + s, 80 + 0.004 * s ** 2]
    >>> (np.round(rope_curve(pl, (100, 80), (1, 0), (0, 1)), 4) + 0.0).tolist()    # (+ 0.0: no "-0.0")
    [0.0, 0.0, 0.004, -50.0, 50.0]
    """
    if polyline is None or len(polyline) < 3:
        return None
    P = np.asarray(polyline, np.float64) - np.asarray(center_xy, np.float64)[None]
    u = np.asarray(across, np.float64)
    ss, tt = P @ u, P @ _normal_toward(u, along)
    if np.ptp(ss) < 4:
        return None
    c2, c1, c0 = np.polyfit(ss, tt, 2)
    return np.array([c0, c1, c2, ss.min(), ss.max()])


def band_mask(shape: tuple[int, int], center_xy, across, s_lo: float, s_hi: float, half_len: float) -> np.ndarray:
    """(H, W) bool band across a stem: from ``s_lo`` to ``s_hi`` pixels along ``across`` from
    ``center_xy``, ``half_len`` pixels either side of that line (normal to ``across``).

    Examples
    --------
    >>> m = band_mask((20, 30), (15, 10), (1, 0), -5, 5, 2)
    >>> np.argwhere(m)[[0, -1]].tolist()       # rows 8..12, columns 10..20
    [[8, 10], [12, 20]]
    """
    import cv2
    c = np.asarray(center_xy, np.float64)
    u = np.asarray(across, np.float64)
    a = np.array([-u[1], u[0]])
    quad = np.array([c + s_lo * u - half_len * a, c + s_hi * u - half_len * a,
                     c + s_hi * u + half_len * a, c + s_lo * u + half_len * a])
    m = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(m, np.round(quad).astype(np.int32), 1)
    return m > 0


def combine_edges(left: TrunkEdges, right: TrunkEdges, frame: TrunkEdges | None = None) -> TrunkEdges:
    """Edges with the left side of ``left`` and the right side of ``right``, both found at the
    same rope; the stem and cross-section directions are ``frame``'s (default ``left``'s).

    Returns
    -------
    TrunkEdges
    """
    frame = frame or left
    u = np.asarray(frame.across, np.float64)
    # each side's point where its own line crosses the frame's cross-section (the sides found on
    # another cross-section, or with another direction, would otherwise tilt the section)
    c = 0.5 * (np.asarray(frame.left_xy, np.float64) + np.asarray(frame.right_xy, np.float64))
    lxy = _on_section(np.asarray(left.left_xy, np.float64), np.asarray(left.along, np.float64), c, u)
    rxy = _on_section(np.asarray(right.right_xy, np.float64), np.asarray(right.along, np.float64), c, u)
    width = float((rxy - lxy) @ u)
    return TrunkEdges(left_xy=lxy, right_xy=rxy, width_px=width, along=frame.along, across=u,
                      edge_rms_px=max(left.edge_rms_px, right.edge_rms_px), n_lines=min(left.n_lines, right.n_lines),
                      points=dict(left=left.points.get("left"), right=right.points.get("right")))


def _on_section(p: np.ndarray, d: np.ndarray, c: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Where the line through ``p`` (2,) along ``d`` (2,) crosses the line through ``c`` along
    ``u``; ``p`` itself where the two are (nearly) parallel."""
    A = np.column_stack([d, -u])
    if abs(np.linalg.det(A)) < 1e-3 * (np.linalg.norm(d) * np.linalg.norm(u) + 1e-12):
        return p
    t, _ = np.linalg.solve(A, c - p)
    return p + t * d


def refit_edges(edges: TrunkEdges, keep: dict) -> TrunkEdges:
    """The edges refitted on a subset of their points, as two parallel lines.

    Parameters
    ----------
    edges : :class:`TrunkEdges` with ``points`` (each side's (N, 2) edge points).
    keep : ``{"left": (N,) bool, "right": (M,) bool}``: the points to keep on each side (a side
        not named keeps all).

    Returns
    -------
    TrunkEdges: the two sides' lines through their kept points with one common direction (points
    beyond 3.5 MAD left out once), on the same cross-section line; ``edges`` itself where a side
    would keep fewer than 3 points. (Points left out for what they are, e.g. a rope's loose end
    beside the stem, often lie on one side of the rope only: a side's own line refitted on the
    rest may tilt; the common direction rests on both sides.)
    """
    c = 0.5 * (edges.left_xy + edges.right_xy)
    u = edges.across
    a = _normal_toward(u, edges.along)
    T, S, L, kept = [], [], [], {}
    for j, side in enumerate(("left", "right")):
        P = np.asarray(edges.points[side], np.float64)
        k = np.asarray(keep.get(side, np.ones(len(P), bool)), bool)
        if k.sum() < 3:
            return edges
        Q = P[k] - c
        T.append(Q @ a)
        S.append(Q @ u)
        L.append(np.full(k.sum(), j))
        kept[side] = P[k]
    t, s_, side_of = np.concatenate(T), np.concatenate(S), np.concatenate(L)
    A = np.c_[side_of == 0, side_of == 1, t].astype(np.float64)
    ok = np.ones(len(t), bool)
    for _ in range(2):
        coef, *_ = np.linalg.lstsq(A[ok], s_[ok], rcond=None)
        r = s_ - A @ coef
        new = np.abs(r) < 3.5 * (np.median(np.abs(r[ok])) + 0.05)
        if min((new & (side_of == 0)).sum(), (new & (side_of == 1)).sum()) < 3:
            break
        ok = new
    coef, *_ = np.linalg.lstsq(A[ok], s_[ok], rcond=None)
    r = (s_ - A @ coef)[ok]
    along = a + coef[2] * u
    return TrunkEdges(left_xy=c + coef[0] * u, right_xy=c + coef[1] * u, width_px=float(coef[1] - coef[0]),
                      along=along / np.linalg.norm(along), across=u, edge_rms_px=float(np.sqrt(np.mean(r ** 2))),
                      n_lines=int(min((ok & (side_of == 0)).sum(), (ok & (side_of == 1)).sum())),
                      points=dict(left=kept["left"][ok[side_of == 0]], right=kept["right"][ok[side_of == 1]]))
