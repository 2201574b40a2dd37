"""Reading the depth map at the roped stem: the stem's front depth at the rope.

Imported by :mod:`.ground` and :mod:`.scale`; imports numpy only. Network perception reads the
nearest depth across the stem (:func:`depth_nearest_across`; decision record
``docs/decisions/stem-depth-read.md``); ground-truth perception, whose depth map is exact, reads
the stem's centre (:func:`depth_at_stem_centre`).
"""
from __future__ import annotations

import numpy as np

from .edges import TrunkEdges
from .perception import Perception

__all__ = ["depth_at", "depth_nearest_across", "depth_at_stem_centre", "stem_front_depth"]


def depth_at(depth: np.ndarray, mask: np.ndarray, xy, radius: float) -> float:
    """Median of the positive ``depth`` (H, W) within ``mask`` (H, W) bool in the square of
    half-side ``radius`` (pixels, at least 1) around the pixel ``xy``; nan where there is none."""
    H, W = depth.shape
    x, y = int(round(xy[0])), int(round(xy[1]))
    r = int(max(1, radius))
    win = depth[max(0, y - r):y + r + 1, max(0, x - r):x + r + 1]
    m = mask[max(0, y - r):y + r + 1, max(0, x - r):x + r + 1] & (win > 0)
    if not m.any():
        return np.nan
    return float(np.median(win[m]))


def depth_nearest_across(depth: np.ndarray, left_xy, right_xy, rows: int = 2, inner: float = 0.9) -> float:
    """The nearest depth on the stem's cross-section: the minimum of ``depth`` (H, W) over the
    segment between the two edge points (its middle ``inner`` fraction), ``+-rows`` pixels
    across it; nan where nothing positive is there.

    The depth network's map is upsampled from its 256-pixel input, where a thin stem is a few
    pixels wide: the background behind it bleeds into its middle, so the middle reads too far
    (decision record ``docs/decisions/stem-depth-read.md``).
    """
    H, W = depth.shape
    L = np.asarray(left_xy, np.float64)
    d = np.asarray(right_xy, np.float64) - L
    n = max(2, int(np.ceil(np.linalg.norm(d))) + 1)
    f = 0.5 + (np.linspace(0.0, 1.0, n) - 0.5) * inner
    P = L[None] + f[:, None] * d[None]
    across = np.array([-d[1], d[0]]) / (np.linalg.norm(d) + 1e-12)
    best = np.inf
    for k in range(-rows, rows + 1):
        Q = np.round(P + k * across).astype(int)
        ok = (Q[:, 0] >= 0) & (Q[:, 0] < W) & (Q[:, 1] >= 0) & (Q[:, 1] < H)
        if ok.any():
            z = depth[Q[ok, 1], Q[ok, 0]]
            z = z[z > 0]
            if z.size:
                best = min(best, float(z.min()))
    return best if np.isfinite(best) else np.nan


def depth_at_stem_centre(perc: Perception, edges: TrunkEdges, offset_xy: np.ndarray) -> float:
    """The median depth at three points of the stem's middle (35, 50 and 65 % of the way between
    its edges, shifted by ``offset_xy`` (2,)), each the median of the tree mask's pixels around it
    (the edge mask's where the tree mask misses the stem there); nan where none has depth."""
    line = np.array([edges.left_xy + f * (edges.right_xy - edges.left_xy) for f in (0.35, 0.5, 0.65)])
    zs = [depth_at(perc.depth, perc.tree_mask, p + offset_xy, 2) for p in line]
    if not np.isfinite(zs).any() and perc.edge_mask is not None:
        # the coarse tree mask misses the stem at the rope: the stem between its edges
        zs = [depth_at(perc.depth, perc.edge_mask, p + offset_xy, 2) for p in line]
    return float(np.nanmedian(zs)) if np.isfinite(zs).any() else np.nan


def stem_front_depth(perc: Perception, edges: TrunkEdges) -> float:
    """The depth of the stem's front at the rope, read just below the rope band (3 rope
    half-thicknesses down the stem): the nearest across the stem from a depth map that is not
    metric (the depth network's), the stem's centre from an exact one (ground truth); nan where
    the map has none there."""
    off = 3 * perc.rope_half_px * edges.along
    if not perc.depth_is_metric:
        return depth_nearest_across(perc.depth, edges.left_xy + off, edges.right_xy + off)
    return depth_at_stem_centre(perc, edges, off)
