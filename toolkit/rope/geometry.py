"""Pixel geometry shared by the rope detectors and their callers: distances from a point to a
rope band, whether a point lies on red that runs on into a band, the tree instance at a point,
the tree-mask run a band crosses; imported by the modules of :mod:`monodbh.toolkit.rope` and by
the pipeline.

Examples
--------
>>> line = np.array([[0.0, 0.0], [10.0, 0.0]], np.float32)
>>> distance_to_vertices(line, (5.0, 3.0)), distance_to_chord(line, (5.0, 3.0))
(5.830951690673828, 3.0)
"""
from __future__ import annotations

import cv2
import numpy as np

from .redness import redness_map

__all__ = ["distance_to_vertices", "distance_to_chord", "distance_to_band", "red_path_to_band",
           "instance_in_window", "instance_at_or_near", "trunk_run"]


def distance_to_vertices(polyline: np.ndarray, xy) -> float:
    """Distance from ``xy`` to the nearest vertex of ``polyline``, in the polyline's own dtype.

    Parameters
    ----------
    polyline : (N, 2) centre line (x, y) pixels; float32 stays float32 (the band detector's
        choice at a tap), pass float64 for float64.
    xy : (x, y) pixels.
    """
    px, py = xy
    return float(np.min(np.hypot(polyline[:, 0] - px, polyline[:, 1] - py)))


def distance_to_chord(polyline: np.ndarray, xy) -> float:
    """Distance from ``xy`` to the segment between the first and last points of ``polyline``
    (float64; the rope finder's candidates are straight).

    Parameters
    ----------
    polyline : (N, 2) centre line (x, y) pixels, N >= 1.
    xy : (x, y) pixels.
    """
    a, b = np.asarray(polyline[0], float), np.asarray(polyline[-1], float)
    p = np.asarray(xy, float)
    d = b - a
    t = float(np.clip((p - a) @ d / max(float(d @ d), 1e-9), 0.0, 1.0))
    return float(np.hypot(*(p - a - t * d)))


def distance_to_band(rope, xy) -> float:
    """Distance from ``xy`` to a found rope's centre line vertices (float64), or to its
    ``center_xy`` when it has no centre line.

    Parameters
    ----------
    rope : a :class:`~monodbh.toolkit.rope.detection.RopeDetection` or candidate
        (``polyline``, ``center_xy``).
    xy : (x, y) pixels.
    """
    p = rope.polyline if rope.polyline is not None and len(rope.polyline) else np.asarray([rope.center_xy])
    return distance_to_vertices(np.asarray(p, np.float64), xy)


def red_path_to_band(img: np.ndarray, rope, xy, *, reach_px: float, level: float = 0.5,
                     min_redness: float = 0.03) -> bool:
    """Whether ``xy`` lies on red that runs on, unbroken, into the band of ``rope``: the marker's
    knot or a loose end hanging from it, which a user may tap instead of the ring.

    The red-ness (:func:`~.redness.redness_map`) is read in a window holding the band and ``xy``;
    a pixel is red at ``level`` x the median red-ness on the band's centre line or more (at least
    ``min_redness``). The red pixels (8-connected) within ``max(3, thickness)`` px of ``xy`` must
    belong to a region that also covers the band's centre line.

    Parameters
    ----------
    img : (H, W, 3) uint8 RGB, the band's pixels.
    rope : a found band (``polyline`` (N, 2), ``thickness_px``).
    xy : (x, y) pixels.
    reach_px : farther than this from the band's centre line, False without looking.
    level, min_redness : the red threshold, as above.

    Examples
    --------
    >>> img = np.full((60, 60, 3), 120, np.uint8)
    >>> img[20:23, 10:40] = (200, 40, 30)           # the ring
    >>> img[20:50, 38:41] = (200, 40, 30)           # a loose end hanging from it
    >>> class Band: polyline = np.array([[10.0, 21.0], [39.0, 21.0]]); thickness_px = 3.0
    >>> red_path_to_band(img, Band, (39, 45), reach_px=40), red_path_to_band(img, Band, (20, 45), reach_px=40)
    (True, False)
    """
    P = np.asarray(rope.polyline if rope.polyline is not None else [rope.center_xy], np.float64).reshape(-1, 2)
    px, py = float(xy[0]), float(xy[1])
    if distance_to_vertices(P, (px, py)) > reach_px:
        return False
    H, W = img.shape[:2]
    r = max(3.0, float(rope.thickness_px or 0.0))
    pad = int(np.ceil(2 * r + 4))
    x0, y0 = max(0, int(min(P[:, 0].min(), px)) - pad), max(0, int(min(P[:, 1].min(), py)) - pad)
    x1, y1 = min(W, int(max(P[:, 0].max(), px)) + pad + 1), min(H, int(max(P[:, 1].max(), py)) + pad + 1)
    if x1 - x0 < 2 or y1 - y0 < 2:
        return False
    F = redness_map(np.ascontiguousarray(img[y0:y1, x0:x1]))
    Q = np.round(P - (x0, y0)).astype(int)
    Q = Q[(Q[:, 0] >= 0) & (Q[:, 0] < x1 - x0) & (Q[:, 1] >= 0) & (Q[:, 1] < y1 - y0)]
    if not len(Q):
        return False
    thr = max(min_redness, level * float(np.median(F[Q[:, 1], Q[:, 0]])))
    _, lab = cv2.connectedComponents((F >= thr).astype(np.uint8), connectivity=8)
    on_band = set(np.unique(lab[Q[:, 1], Q[:, 0]]).tolist()) - {0}
    yy, xx = np.mgrid[y0:y1, x0:x1]
    near = np.hypot(xx - px, yy - py) <= r
    return bool(on_band & (set(np.unique(lab[near]).tolist()) - {0}))


def instance_in_window(instance: np.ndarray, xy, radius: int) -> int:
    """The most frequent tree id (> 0) in the square window of half side ``radius`` around
    ``xy`` (rounded, not clipped to the image); 0 when the window holds none.

    Parameters
    ----------
    instance : (H, W) int tree instance ids (0 = none).
    xy : (x, y) pixels.
    radius : int, pixels.
    """
    x, y = int(round(xy[0])), int(round(xy[1]))
    win = instance[max(0, y - radius):y + radius + 1, max(0, x - radius):x + radius + 1]
    ids = win[win > 0]
    if ids.size == 0:
        return 0
    return int(np.bincount(ids).argmax())


def instance_at_or_near(instance: np.ndarray, xy, radius: float) -> int:
    """The tree id under ``xy`` (clipped into the image), else the most frequent one within
    ``radius`` pixels of it (at least 2, :func:`instance_in_window`); 0 if none.

    Parameters
    ----------
    instance : (H, W) int tree instance ids (0 = none).
    xy : (x, y) pixels.
    radius : pixels.
    """
    H, W = instance.shape
    x, y = int(np.clip(round(xy[0]), 0, W - 1)), int(np.clip(round(xy[1]), 0, H - 1))
    if instance[y, x] > 0:
        return int(instance[y, x])
    return instance_in_window(instance, (x, y), int(max(2, round(radius))))


def trunk_run(tree_mask: np.ndarray, poly: np.ndarray, xc: float) -> tuple[int, int]:
    """Columns ``[l, r]`` of the tree-mask run along the (extended) rope curve that contains ``xc``.

    Parameters
    ----------
    tree_mask : (H, W) bool.
    poly : (N, 2) rope centre line (x, y), x increasing.
    xc : column on the rope; a mask pixel within 3 columns of it is taken when it is off the mask.

    Returns
    -------
    (l, r) : the run's first and last column; ``(0, -1)`` when there is no mask near ``xc``.
    """
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
