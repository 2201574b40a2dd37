"""How well calibration views cover the image, scored like ROS ``camera_calibration``.

Each view gets ``(X, Y, size, skew)`` in [0, 1] (``camera_calibration/calibrator.py``,
``Calibrator.get_parameters``): X and Y are the board's mean corner position with the image
shrunk by half the board size on every side, size is ``sqrt(board area / image area)`` and
skew is ``2 * |90 deg - angle at the top-right outer corner|`` (radians, capped at 1). Over
all views, progress per parameter is ``(max - min) / range`` capped at 1, with ranges
``X 0.7, Y 0.7, size 0.4, skew 0.5`` and the minima of size and skew taken as 0 (ROS does not
reward small or unskewed views). ROS calls a data set good enough when all four reach 1.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .board import Board, Detection

__all__ = ["CoverageScore", "view_parameters", "coverage_scores", "coverage_advice",
           "PARAM_RANGES"]

#: ROS camera_calibration ``param_ranges`` for X, Y, size, skew.
PARAM_RANGES = (0.7, 0.7, 0.4, 0.5)
_NAMES = ("X", "Y", "size", "skew")


@dataclass(frozen=True)
class CoverageScore:
    """Coverage of one parameter over all views: ``min``, ``max`` and ``progress`` in [0, 1]."""

    name: str
    min: float
    max: float
    progress: float


def _outside_corners(det: Detection, board: Board) -> np.ndarray | None:
    """(4, 2) up-left, up-right, down-right, down-left corners of the detected board."""
    cols, rows = board.corner_grid
    pts = np.asarray(det.corners, np.float64).reshape(-1, 2)
    ids = np.asarray(det.ids).reshape(-1)
    if len(ids) == cols * rows and np.array_equal(ids, np.arange(cols * rows)):
        return np.array([pts[0], pts[cols - 1], pts[-1], pts[-cols]])
    # Partial (ChArUco) detection: the largest grid rectangle with all four corners seen,
    # like ROS's _get_largest_rectangle_corners.
    where = {int(i): k for k, i in enumerate(ids)}
    gx, gy = ids % cols, ids // cols
    best, best_area = None, 0
    for a in range(len(ids)):
        for b in range(len(ids)):
            x0, y0, x1, y1 = gx[a], gy[a], gx[b], gy[b]
            if x1 <= x0 or y1 <= y0:
                continue
            area = (x1 - x0) * (y1 - y0)
            if area <= best_area:
                continue
            ur, dl = y0 * cols + x1, y1 * cols + x0
            if ur in where and dl in where:
                best_area = area
                best = (a, where[ur], b, where[dl])
    if best is None:
        return None
    return pts[list(best)]


def view_parameters(det: Detection, board: Board, image_size: Sequence[int]) -> tuple[float, ...] | None:
    """ROS coverage parameters ``(X, Y, size, skew)`` of one detection, or None if degenerate.

    Parameters
    ----------
    det : Detection
        Detected corners, (N, 2) pixels.
    board : Board
        The board.
    image_size : tuple of int
        ``(width, height)``.
    """
    width, height = image_size
    quad = _outside_corners(det, board)
    if quad is None:
        return None
    ul, ur, dr, dl = quad
    a, b, c = ur - ul, dr - ur, dl - dr
    p, q = b + c, a + b
    area = abs(p[0] * q[1] - p[1] * q[0]) / 2.0
    ab, cb = ul - ur, dr - ur
    den = np.linalg.norm(ab) * np.linalg.norm(cb)
    if den <= 0 or area <= 0:
        return None
    angle = math.acos(float(np.clip(np.dot(ab, cb) / den, -1.0, 1.0)))
    skew = min(1.0, 2.0 * abs(math.pi / 2.0 - angle))
    border = math.sqrt(area)
    pts = np.asarray(det.corners, np.float64).reshape(-1, 2)
    px = min(1.0, max(0.0, (pts[:, 0].mean() - border / 2) / max(width - border, 1e-9)))
    py = min(1.0, max(0.0, (pts[:, 1].mean() - border / 2) / max(height - border, 1e-9)))
    size = math.sqrt(area / (width * height))
    return (px, py, size, skew)


def coverage_scores(params: Sequence[Sequence[float]]) -> list[CoverageScore]:
    """Combine per-view parameters into ROS-style progress for X, Y, size and skew.

    Parameters
    ----------
    params : sequence of (4,) tuples
        :func:`view_parameters` of the views used.

    Returns
    -------
    list of CoverageScore
        Four scores in the order X, Y, size, skew (progress 0 when ``params`` is empty).
    """
    if len(params) == 0:
        return [CoverageScore(n, 0.0, 0.0, 0.0) for n in _NAMES]
    P = np.asarray(params, dtype=np.float64).reshape(-1, 4)
    lo, hi = P.min(axis=0), P.max(axis=0)
    lo[2:] = 0.0  # don't reward small size or skew
    out = []
    for n, l, h, r in zip(_NAMES, lo, hi, PARAM_RANGES):
        out.append(CoverageScore(n, float(l), float(h), float(min((h - l) / r, 1.0))))
    return out


def coverage_advice(scores: Sequence[CoverageScore], n_views: int) -> list[str]:
    """Plain-language advice for the parameters whose progress is below 1."""
    tips = []
    s = {c.name: c for c in scores}
    if s["X"].progress < 1.0:
        tips.append(f"X coverage {s['X'].progress:.0%}: add views with the board near the left "
                    f"and right edges of the frame")
    if s["Y"].progress < 1.0:
        tips.append(f"Y coverage {s['Y'].progress:.0%}: add views with the board near the top "
                    f"and bottom edges of the frame")
    if s["size"].progress < 1.0:
        tips.append(f"size coverage {s['size'].progress:.0%}: add close-up views where the "
                    f"board fills most of the frame")
    if s["skew"].progress < 1.0:
        tips.append(f"skew coverage {s['skew'].progress:.0%}: add views with the board tilted "
                    f"30-45 degrees toward and away from the camera, about both axes")
    if n_views < 10:
        tips.append(f"only {n_views} views used: 15-25 views all over the frame give steadier "
                    f"intrinsics")
    return tips
