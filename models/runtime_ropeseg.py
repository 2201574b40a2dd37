"""onnxruntime predictor of the rope finder (numpy + cv2 + onnxruntime; on the measuring path).

The band detector (``monodbh.toolkit.rope``) needs a rope redder than its surroundings, and the
mask-guided stem search (``monodbh.toolkit.rope_stem``) needs the segmenter to have found the
roped stem. Where both fail, this small fully convolutional network (``modeling/ropeseg.py``)
looks for the rope in the whole photo, without masks.

Tiling (:meth:`RopeFinder.logit_map`)
    The network's graph has a fixed tile of ``TILE`` x ``TILE`` photo pixels (batch 1). The
    working image is covered by tiles overlapping by ``2 * BORDER`` pixels; of each tile's
    output only the middle is kept (the tile's border has less context), except along the
    photo's own border. Outside the photo the tile is black, as in training.

Candidates (:func:`rope_components`)
    Output pixels (2 x 2 photo pixels) with log-odds above ``LOGIT_LO`` form 8-connected
    components; pieces of one rope broken by an occluding twig are merged when they lie on one
    line. Each candidate: the centre, direction, length and thickness from the probability-
    weighted moments of its pixels (photo pixels), its peak log-odds ``peak``, and ``mass``,
    the summed probability (about the rope's visible length in output pixels).

This module imports only numpy, cv2 and ``monodbh.models.runtime``.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from monodbh.models.runtime import OnnxPredictor
from monodbh.models.runtime_gan import normalize_rgb

__all__ = ["TILE", "BORDER", "LOGIT_LO", "KNOT_MAX_TILT_DEG", "KNOT_MAX_RADIUS_FRACTION", "RopeComponent",
           "tile_origins", "knot_band", "rope_components", "RopeFinder"]

TILE: int = 384       #: the shipped graph's tile side (photo pixels; the runtime reads it from the graph)
BORDER: int = 16      #: photo pixels of each tile's border not kept where a neighbour covers them
LOGIT_LO: float = 0.0  #: output pixels above these log-odds belong to a component
#: a rope piece too thick for a band (knot and hanging ends) is searched for its band
#: (:func:`knot_band`): a line within this angle of horizontal ...
KNOT_MAX_TILT_DEG: float = 40.0
#: ... through a piece of strands no thicker (inscribed radius) than this fraction of the band
KNOT_MAX_RADIUS_FRACTION: float = 0.25


@dataclass
class RopeComponent:
    """One rope hypothesis of the finder, in photo pixels of the image it ran on.

    Attributes
    ----------
    center_xy : (x, y) probability-weighted centre.
    direction : unit (dx, dy) along the band, dx >= 0.
    length_px : extent along the band (photo pixels).
    thickness_px : extent across it (4 x the weighted standard deviation, photo pixels, >= 1).
    peak : highest log-odds of its output pixels.
    mass : summed probability of its output pixels.
    n : number of output pixels.
    polyline : (2, 2) float32 end points (x, y) along the band.
    trimmed : the piece was too thick for a band (a knot with hanging ends) and only its band
        across the stem is described (:func:`knot_band`).
    """
    center_xy: tuple[float, float]
    direction: tuple[float, float]
    length_px: float
    thickness_px: float
    peak: float
    mass: float
    n: int
    polyline: np.ndarray = field(repr=False, default=None)
    trimmed: bool = False


def tile_origins(size: int, tile: int = TILE, border: int = BORDER) -> list[int]:
    """Tile starts covering ``[0, size)`` with overlaps of ``2 * border`` (even, may be < 0 when size < tile).

    Examples
    --------
    >>> tile_origins(1000)
    [0, 352, 616]
    """
    if size <= tile:
        return [0]
    step = tile - 2 * border
    xs = list(range(0, size - tile, step)) + [size - tile]
    return sorted({x // 2 * 2 for x in xs})


def _moments(ys: np.ndarray, xs: np.ndarray, w: np.ndarray):
    w = w / w.sum()
    cx, cy = float((w * xs).sum()), float((w * ys).sum())
    dx, dy = xs - cx, ys - cy
    C = np.array([[(w * dx * dx).sum(), (w * dx * dy).sum()], [(w * dx * dy).sum(), (w * dy * dy).sum()]])
    ev, evec = np.linalg.eigh(C)
    d = evec[:, 1]
    if d[0] < 0:
        d = -d
    return cx, cy, d, ev


def _extent(ys: np.ndarray, xs: np.ndarray, w: np.ndarray, stride: int):
    """Weighted centre (cells), direction, positions along it (cells), length and thickness
    (photo pixels: 4 weighted standard deviations across, >= 1) of a piece's cells."""
    cx, cy, d, ev = _moments(ys.astype(np.float64), xs.astype(np.float64), w)
    t = (xs - cx) * d[0] + (ys - cy) * d[1]
    length = (float(t.max() - t.min()) + 1.0) * stride
    thick = max(1.0, 4.0 * np.sqrt(max(ev[0], 0.0)) * stride)
    return cx, cy, d, t, length, thick


def knot_band(ys: np.ndarray, xs: np.ndarray, max_tilt_deg: float = KNOT_MAX_TILT_DEG,
              max_radius_frac: float = KNOT_MAX_RADIUS_FRACTION) -> np.ndarray | None:
    """The band across the stem of a rope piece that also holds its knot and hanging ends.

    A rope tied round a stem is often knotted at the front with its ends hanging down: the
    finder then marks one connected piece shaped like a "T" or an "L", too thick for a band by
    its moments. Its band is the strongest near-horizontal straight line through the piece
    (``cv2.HoughLines`` on the piece's cells, normals within ``max_tilt_deg`` of vertical),
    the cells within 1.5 cells of it, their longest run with gaps of at most 3 cells.

    A piece is only trimmed when it is built of thin strands: its largest inscribed radius
    (``cv2.distanceTransform``) is at most ``max_radius_frac`` of the band's length (a red
    jacket or a cluster of red leaves is a blob, not strands).

    Parameters
    ----------
    ys, xs : (N,) int output-cell coordinates of the piece.

    Returns
    -------
    (N,) bool: the band's cells, or None when the piece has no such band.

    Examples
    --------
    >>> ys = np.r_[np.full(30, 10), np.arange(11, 25)]          # a band with a hanging end
    >>> xs = np.r_[np.arange(30), np.full(14, 20)]
    >>> keep = knot_band(ys, xs)
    >>> int(keep.sum()), bool(keep[:30].all())
    (31, True)
    """
    ys, xs = np.asarray(ys, np.int64), np.asarray(xs, np.int64)
    if len(xs) < 6:
        return None
    x0, y0 = int(xs.min()) - 2, int(ys.min()) - 2
    m = np.zeros((int(ys.max()) - y0 + 3, int(xs.max()) - x0 + 3), np.uint8)
    m[ys - y0, xs - x0] = 1
    radius = float(cv2.distanceTransform(m, cv2.DIST_L2, 3).max())
    t = np.deg2rad(max_tilt_deg)
    lines = cv2.HoughLines(m * 255, 1, np.pi / 180, max(4, int(0.3 * max(m.shape))),
                           min_theta=np.pi / 2 - t, max_theta=np.pi / 2 + t)
    if lines is None or len(lines) == 0:       # OpenCV 5 returns an empty array, 4.x None
        return None
    rho, theta = (float(v) for v in lines[0, 0])
    X, Y = xs - x0, ys - y0
    on = np.abs(X * np.cos(theta) + Y * np.sin(theta) - rho) <= 1.5
    if on.sum() < 4:
        return None
    along = X * -np.sin(theta) + Y * np.cos(theta)
    idx = np.flatnonzero(on)
    order = idx[np.argsort(along[idx])]
    a = along[order]
    cuts = np.flatnonzero(np.diff(a) > 3.0)
    starts, ends = np.r_[0, cuts + 1], np.r_[cuts, len(a) - 1]
    k = int(np.argmax(a[ends] - a[starts]))
    run = order[starts[k]:ends[k] + 1]
    length = float(a[ends[k]] - a[starts[k]]) + 1.0
    if radius > max(2.0, max_radius_frac * length):
        return None
    keep = np.zeros(len(xs), bool)
    keep[run] = True
    return keep


def rope_components(logit: np.ndarray, stride: int = 2, lo: float = LOGIT_LO,
                    max_components: int = 8) -> list[RopeComponent]:
    """Rope candidates from an output map ``logit`` ``(h, w)`` (output pixel ``(i, j)`` covers
    photo pixels ``stride * (i, j)`` to ``stride * (i, j) + stride - 1``), best ``mass`` first.

    Examples
    --------
    >>> z = np.full((40, 60), -6.0, np.float32); z[20, 10:50] = 4.0
    >>> c = rope_components(z)[0]
    >>> [round(v) for v in c.center_xy], round(c.length_px), c.n
    ([60, 40], 80, 40)
    """
    z = np.asarray(logit, np.float32)
    if z.ndim != 2:
        raise ValueError(f"rope_components: logit must be (h, w), got {z.shape}")
    m = (z > lo).astype(np.uint8)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    if n <= 1:
        return []
    p = 1.0 / (1.0 + np.exp(-np.clip(z, -30, 30)))
    # merge collinear pieces: label image dilated along each piece's direction would be costly;
    # pieces are few, so join pairs whose ends are close along a common line
    groups = list(range(n))

    def root(a: int) -> int:
        while groups[a] != a:
            groups[a] = groups[groups[a]]
            a = groups[a]
        return a

    pieces = {}
    for k in range(1, n):
        if stats[k, cv2.CC_STAT_AREA] >= 4000:
            continue
        # the piece's own bounding box, not the whole map, per piece
        x0, y0, bw, bh = (int(stats[k, j]) for j in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP,
                                                       cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT))
        ys, xs = np.nonzero(lab[y0:y0 + bh, x0:x0 + bw] == k)
        ys, xs = ys + y0, xs + x0
        cx, cy, d, ev = _moments(ys.astype(np.float64), xs.astype(np.float64), p[ys, xs].astype(np.float64))
        half = 2.0 * np.sqrt(max(ev[1], 0.0)) + 0.5
        pieces[k] = (ys, xs, np.array([cx, cy]), d, half)
    ks = sorted(pieces)
    for a_i, a in enumerate(ks):
        for b in ks[a_i + 1:]:
            _, _, ca, da, ha = pieces[a]
            _, _, cb, db, hb = pieces[b]
            v = cb - ca
            dist = float(np.hypot(*v))
            if dist > 2.5 * (ha + hb) + 4 or abs(float(da @ db)) < 0.94:
                continue
            off = abs(float(v[0] * da[1] - v[1] * da[0]))      # across piece a's line
            if off <= 2.0 + 0.05 * dist:
                groups[root(b)] = root(a)
    out = []
    for r in {root(k) for k in ks}:
        members = [k for k in ks if root(k) == r]
        ys = np.concatenate([pieces[k][0] for k in members])
        xs = np.concatenate([pieces[k][1] for k in members])
        w = p[ys, xs].astype(np.float64)
        cx, cy, d, t, length, thick = _extent(ys, xs, w, stride)
        trimmed = False
        if length < 3.0 * thick:
            # too thick for a band: a knot with hanging ends? keep the band across the stem
            keep = knot_band(ys, xs)
            if keep is not None:
                ys, xs, w, trimmed = ys[keep], xs[keep], w[keep], True
                cx, cy, d, t, length, thick = _extent(ys, xs, w, stride)
        c = (stride * cx + 0.5 * (stride - 1), stride * cy + 0.5 * (stride - 1))
        # end points: the outer photo pixels of the end cells (the extent is a whole number of cells)
        lo = stride * t.min() - 0.5 * (stride - 1)
        hi = stride * t.max() + 0.5 * (stride - 1)
        ends = np.array([[c[0] + lo * d[0], c[1] + lo * d[1]], [c[0] + hi * d[0], c[1] + hi * d[1]]], np.float32)
        out.append(RopeComponent(center_xy=(float(c[0]), float(c[1])), direction=(float(d[0]), float(d[1])),
                                 length_px=length, thickness_px=float(thick), peak=float(z[ys, xs].max()),
                                 mass=float(w.sum()), n=int(len(xs)), polyline=ends, trimmed=trimmed))
    out.sort(key=lambda c: -c.mass)
    return out[:max_components]


class RopeFinder(OnnxPredictor):
    """The rope finder (kind ``"ropeseg"``): rope log-odds over a whole photo, no masks needed.

    Parameters
    ----------
    path : path, optional
        ONNX file (input ``image`` ``(1, 3, TILE, TILE)``, output ``logit``
        ``(1, 1, TILE/2, TILE/2)``); default the shipped ``models/ropeseg_int8.onnx``.
    threads, manifest : as :class:`monodbh.models.runtime.OnnxPredictor`.

    Examples
    --------
    >>> finder = RopeFinder()                          # doctest: +SKIP
    >>> comps = rope_components(finder.logit_map(rgb))  # doctest: +SKIP
    """

    kind = "ropeseg"

    def __init__(self, path: str | os.PathLike | None = None, threads: int = 2,
                 manifest: dict[str, Any] | None = None) -> None:
        super().__init__(self.kind, path, threads, manifest)
        shape = tuple(self.input_shape("image"))
        if shape[2] != shape[3] or shape[2] % 2:
            raise ValueError(f"{self.path}: rope finder tiles must be square and even, got {shape}")
        self.tile = int(shape[2])

    def logit_map(self, rgb: np.ndarray) -> np.ndarray:
        """``(H, W, 3)`` uint8 -> ``(ceil(H/2), ceil(W/2))`` float32 rope log-odds per 2 x 2 pixels."""
        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ValueError(f"RopeFinder.logit_map: need (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
        H, W = rgb.shape[:2]
        T, B = self.tile, BORDER
        out = np.full(((H + 1) // 2, (W + 1) // 2), -30.0, np.float32)
        xs, ys = tile_origins(W, T, B), tile_origins(H, T, B)
        for y0 in ys:
            for x0 in xs:
                tile = np.zeros((T, T, 3), np.uint8)
                part = rgb[y0:y0 + T, x0:x0 + T]
                tile[:part.shape[0], :part.shape[1]] = part
                z = self.run({"image": normalize_rgb(tile)[None]})["logit"][0, 0]
                # keep the middle of the tile, or up to the photo's edge where no neighbour covers it
                l = 0 if x0 == xs[0] else B
                t = 0 if y0 == ys[0] else B
                r = T if x0 == xs[-1] else T - B
                b = T if y0 == ys[-1] else T - B
                oy, ox = (y0 + t) // 2, (x0 + l) // 2
                h_, w_ = min(out.shape[0] - oy, (b - t) // 2), min(out.shape[1] - ox, (r - l) // 2)
                if h_ > 0 and w_ > 0:
                    out[oy:oy + h_, ox:ox + w_] = z[t // 2:t // 2 + h_, l // 2:l // 2 + w_]
        return out

    def components(self, rgb: np.ndarray) -> list[RopeComponent]:
        """:func:`rope_components` of :meth:`logit_map` (photo pixels of ``rgb``), best first."""
        return rope_components(self.logit_map(rgb))

    def components_near(self, rgb: np.ndarray, xy) -> list[RopeComponent]:
        """:meth:`components` of one tile centred on ``xy`` (clamped to the photo), in photo pixels
        of ``rgb``: a look at one place for the cost of one tile (a 12 MP photo's working image
        is 20 tiles).

        Parameters
        ----------
        rgb : (H, W, 3) uint8.
        xy : (x, y) photo pixel the tile is centred on.
        """
        rgb = np.asarray(rgb)
        H, W = rgb.shape[:2]
        T = self.tile
        x0 = int(np.clip(round(float(xy[0]) - T / 2), 0, max(W - T, 0))) // 2 * 2
        y0 = int(np.clip(round(float(xy[1]) - T / 2), 0, max(H - T, 0))) // 2 * 2
        comps = self.components(np.ascontiguousarray(rgb[y0:y0 + T, x0:x0 + T]))
        for c in comps:
            c.center_xy = (c.center_xy[0] + x0, c.center_xy[1] + y0)
            c.polyline = c.polyline + np.array([x0, y0], np.float32)
        return comps
