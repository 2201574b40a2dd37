"""Pixel geometry shared by the rope detectors and their callers: distances from a point to a
rope band, the tree instance at a point, the tree-mask run a band crosses; imported by the
modules of :mod:`monodbh.toolkit.rope` and by the pipeline.

Examples
--------
>>> line = np.array([[0.0, 0.0], [10.0, 0.0]], np.float32)
>>> distance_to_vertices(line, (5.0, 3.0)), distance_to_chord(line, (5.0, 3.0))
(5.830951690673828, 3.0)
"""
from __future__ import annotations

import numpy as np

__all__ = ["distance_to_vertices", "distance_to_chord", "distance_to_band", "instance_in_window",
           "instance_at_or_near", "trunk_run"]


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
