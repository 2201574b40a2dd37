"""The rope finder's runtime (network kind ``rope_finder``): rope log-odds over a whole photo, and
the rope candidates read off them.

The band detector (``monodbh.toolkit.rope``) needs a rope redder than its surroundings, and the
mask-guided stem search (``monodbh.toolkit.rope.stem_search``) needs the segmenter to have found the
roped stem. Where both fail, this small fully convolutional network looks for the rope in the
whole photo, without masks.

Tiling (:meth:`RopeFinder.logit_map`)
    The network's graph has a fixed tile of ``TILE`` x ``TILE`` photo pixels (batch 1). The
    working image is covered by tiles overlapping by ``2 * border_px`` pixels
    (:class:`RopeFinderConfig`); of each tile's output only the middle is kept (the tile's border
    has less context), except along the photo's own border. Outside the photo the tile is
    black, as in training.

Candidates (:func:`rope_components`)
    Output pixels (2 x 2 photo pixels) with log-odds above ``logit_lo`` form 8-connected
    components; pieces of one rope broken by an occluding twig are merged when they lie on one
    line. Each candidate: the centre, direction, length and thickness from the probability-
    weighted moments of its pixels (photo pixels), its peak log-odds ``peak``, and ``mass``,
    the summed probability (about the rope's visible length in output pixels).

Imported by ``monodbh.toolkit`` and the rope finder's training code; imports numpy, cv2 and
``monodbh.models.runtime.common`` only.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from monodbh.models.runtime.common import OnnxPredictor, normalize_rgb

__all__ = ["TILE", "RopeFinderConfig", "RopeComponent", "tile_origins", "knot_band", "rope_components",
           "RopeFinder"]

#: the shipped graph's tile side (photo pixels): a structural fact of the trained network (the
#: runtime reads it from the graph)
TILE: int = 384


@dataclass(frozen=True)
class RopeFinderConfig:
    """How the rope finder's output is put together and read (``docs/decisions/rope-finder.md``)."""

    #: photo pixels of each tile's border not kept where a neighbouring tile covers them
    border_px: int = 16
    #: output pixels above these log-odds belong to a candidate
    logit_lo: float = 0.0
    #: a connected piece of at least this many output pixels is not a rope (a red jacket or bush)
    max_piece_cells: int = 4000
    #: two pieces merge when their centres are at most this many (summed) half-lengths apart ...
    merge_reach: float = 2.5
    #: ... plus this many output pixels ...
    merge_gap_cells: float = 4.0
    #: ... their directions agree (|cos| at least this) ...
    merge_min_cos: float = 0.94
    #: ... and the second centre lies within this many output pixels of the first piece's line ...
    merge_max_offset_cells: float = 2.0
    #: ... plus this fraction of the distance between their centres
    merge_offset_per_cell: float = 0.05
    #: a candidate shorter than this many thicknesses is too thick for a band: its knot band is sought
    band_min_elongation: float = 3.0
    #: the knot band (:func:`knot_band`) is a line within this angle of horizontal (degrees) ...
    knot_max_tilt_deg: float = 40.0
    #: ... through a piece of strands no thicker (inscribed radius) than this fraction of the band
    knot_max_radius_fraction: float = 0.25
    #: candidates kept, best mass first
    max_components: int = 8


_DEFAULT = RopeFinderConfig()


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


def tile_origins(size: int, tile: int = TILE, border: int = _DEFAULT.border_px) -> list[int]:
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


def knot_band(ys: np.ndarray, xs: np.ndarray, config: RopeFinderConfig | None = None) -> np.ndarray | None:
    """The band across the stem of a rope piece that also holds its knot and hanging ends.

    A rope tied round a stem is often knotted at the front with its ends hanging down: the
    finder then marks one connected piece shaped like a "T" or an "L", too thick for a band by
    its moments. Its band is the strongest near-horizontal straight line through the piece
    (``cv2.HoughLines`` on the piece's cells, normals within ``config.knot_max_tilt_deg`` of
    vertical),
    the cells within 1.5 cells of it, their longest run with gaps of at most 3 cells.

    A piece is only trimmed when it is built of thin strands: its largest inscribed radius
    (``cv2.distanceTransform``) is at most ``config.knot_max_radius_fraction`` of the band's length (a red
    jacket or a cluster of red leaves is a blob, not strands).

    Parameters
    ----------
    ys, xs : (N,) int output-cell coordinates of the piece.
    config : :class:`RopeFinderConfig`, optional (default: its defaults).

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
    cfg = config or _DEFAULT
    ys, xs = np.asarray(ys, np.int64), np.asarray(xs, np.int64)
    if len(xs) < 6:
        return None
    x0, y0 = int(xs.min()) - 2, int(ys.min()) - 2
    m = np.zeros((int(ys.max()) - y0 + 3, int(xs.max()) - x0 + 3), np.uint8)
    m[ys - y0, xs - x0] = 1
    radius = float(cv2.distanceTransform(m, cv2.DIST_L2, 3).max())
    t = np.deg2rad(cfg.knot_max_tilt_deg)
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
    if radius > max(2.0, cfg.knot_max_radius_fraction * length):
        return None
    keep = np.zeros(len(xs), bool)
    keep[run] = True
    return keep


def _pieces(z: np.ndarray, p: np.ndarray, cfg: RopeFinderConfig) -> dict:
    """The 8-connected pieces of the output cells above ``cfg.logit_lo``: piece label ->
    ``(ys, xs, centre (2,), direction (2,), half-length)`` (output cells; big blobs left out)."""
    m = (z > cfg.logit_lo).astype(np.uint8)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    pieces = {}
    for k in range(1, n):
        if stats[k, cv2.CC_STAT_AREA] >= cfg.max_piece_cells:
            continue
        # the piece's own bounding box, not the whole map, per piece
        x0, y0, bw, bh = (int(stats[k, j]) for j in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP,
                                                       cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT))
        ys, xs = np.nonzero(lab[y0:y0 + bh, x0:x0 + bw] == k)
        ys, xs = ys + y0, xs + x0
        cx, cy, d, ev = _moments(ys.astype(np.float64), xs.astype(np.float64), p[ys, xs].astype(np.float64))
        half = 2.0 * np.sqrt(max(ev[1], 0.0)) + 0.5
        pieces[k] = (ys, xs, np.array([cx, cy]), d, half)
    return pieces


def _collinear_groups(pieces: dict, cfg: RopeFinderConfig) -> list[list[int]]:
    """The pieces' labels grouped into ropes: pairs whose ends are close along a common line join
    (pieces are few, so pairs are tried rather than the label image dilated along each piece)."""
    groups = {k: k for k in pieces}

    def root(a: int) -> int:
        while groups[a] != a:
            groups[a] = groups[groups[a]]
            a = groups[a]
        return a

    ks = sorted(pieces)
    for a_i, a in enumerate(ks):
        for b in ks[a_i + 1:]:
            _, _, ca, da, ha = pieces[a]
            _, _, cb, db, hb = pieces[b]
            v = cb - ca
            dist = float(np.hypot(*v))
            if dist > cfg.merge_reach * (ha + hb) + cfg.merge_gap_cells or abs(float(da @ db)) < cfg.merge_min_cos:
                continue
            off = abs(float(v[0] * da[1] - v[1] * da[0]))      # across piece a's line
            if off <= cfg.merge_max_offset_cells + cfg.merge_offset_per_cell * dist:
                groups[root(b)] = root(a)
    return [[k for k in ks if root(k) == r] for r in {root(k) for k in ks}]


def _component(z: np.ndarray, ys: np.ndarray, xs: np.ndarray, w: np.ndarray, stride: int,
               cfg: RopeFinderConfig) -> RopeComponent:
    """One candidate from its output cells ``(ys, xs)`` and their probabilities ``w``, in photo pixels."""
    cx, cy, d, t, length, thick = _extent(ys, xs, w, stride)
    trimmed = False
    if length < cfg.band_min_elongation * thick:
        # too thick for a band: a knot with hanging ends? keep the band across the stem
        keep = knot_band(ys, xs, cfg)
        if keep is not None:
            ys, xs, w, trimmed = ys[keep], xs[keep], w[keep], True
            cx, cy, d, t, length, thick = _extent(ys, xs, w, stride)
    c = (stride * cx + 0.5 * (stride - 1), stride * cy + 0.5 * (stride - 1))
    # end points: the outer photo pixels of the end cells (the extent is a whole number of cells)
    lo = stride * t.min() - 0.5 * (stride - 1)
    hi = stride * t.max() + 0.5 * (stride - 1)
    ends = np.array([[c[0] + lo * d[0], c[1] + lo * d[1]], [c[0] + hi * d[0], c[1] + hi * d[1]]], np.float32)
    return RopeComponent(center_xy=(float(c[0]), float(c[1])), direction=(float(d[0]), float(d[1])),
                         length_px=length, thickness_px=float(thick), peak=float(z[ys, xs].max()),
                         mass=float(w.sum()), n=int(len(xs)), polyline=ends, trimmed=trimmed)


def rope_components(logit: np.ndarray, stride: int = 2,
                    config: RopeFinderConfig | None = None) -> list[RopeComponent]:
    """Rope candidates from an output map ``logit`` ``(h, w)`` (output pixel ``(i, j)`` covers
    photo pixels ``stride * (i, j)`` to ``stride * (i, j) + stride - 1``), best ``mass`` first.

    Parameters
    ----------
    logit : (h, w) float
        The finder's log-odds (:meth:`RopeFinder.logit_map`).
    stride : int
        Photo pixels per output pixel.
    config : :class:`RopeFinderConfig`, optional (default: its defaults).

    Examples
    --------
    >>> z = np.full((40, 60), -6.0, np.float32); z[20, 10:50] = 4.0
    >>> c = rope_components(z)[0]
    >>> [round(v) for v in c.center_xy], round(c.length_px), c.n
    ([60, 40], 80, 40)
    """
    cfg = config or _DEFAULT
    z = np.asarray(logit, np.float32)
    if z.ndim != 2:
        raise ValueError(f"rope_components: logit must be (h, w), got {z.shape}")
    if not (z > cfg.logit_lo).any():
        return []
    p = 1.0 / (1.0 + np.exp(-np.clip(z, -30, 30)))
    pieces = _pieces(z, p, cfg)
    out = []
    for members in _collinear_groups(pieces, cfg):
        ys = np.concatenate([pieces[k][0] for k in members])
        xs = np.concatenate([pieces[k][1] for k in members])
        out.append(_component(z, ys, xs, p[ys, xs].astype(np.float64), stride, cfg))
    out.sort(key=lambda c: -c.mass)
    return out[:cfg.max_components]


class RopeFinder(OnnxPredictor):
    """The rope finder (kind ``"rope_finder"``): rope log-odds over a whole photo, no masks needed.

    Parameters
    ----------
    path : path, optional
        ONNX file (input ``image`` ``(1, 3, TILE, TILE)``, output ``logit``
        ``(1, 1, TILE/2, TILE/2)``); default the shipped ``models/rope_finder_int8.onnx``.
    threads, manifest, spin : as :class:`~monodbh.models.runtime.common.OnnxPredictor`.
    config : :class:`RopeFinderConfig`, optional (default: its defaults).

    Examples
    --------
    >>> finder = RopeFinder()                          # doctest: +SKIP
    >>> comps = rope_components(finder.logit_map(rgb))  # doctest: +SKIP
    """

    kind = "rope_finder"

    def __init__(self, path: str | os.PathLike | None = None, threads: int = 2,
                 manifest: dict[str, Any] | None = None, *, config: RopeFinderConfig | None = None,
                 spin: bool = False) -> None:
        super().__init__(self.kind, path, threads, manifest, spin=spin)
        self.config = config or _DEFAULT
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
        T, B = self.tile, self.config.border_px
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
        return rope_components(self.logit_map(rgb), config=self.config)

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
