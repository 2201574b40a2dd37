"""The ground plane around the roped stem, fitted to the depth map's ground points.

Imported by :mod:`.measure` (an up direction and, in :mod:`.scale`, the scale sources
``ground_plane`` and ``camera_height``); imports :mod:`.fits` and :mod:`.depth_read`.
"""
from __future__ import annotations

import numpy as np

from .depth_read import depth_at
from .edges import TrunkEdges
from .fits import PlaneFit, fit_plane_ransac
from .perception import Perception

__all__ = ["ground_plane"]


def ground_plane(perc: Perception, edges: TrunkEdges, up_hint: np.ndarray | None) -> tuple[PlaneFit | None, str]:
    """RANSAC plane on depth-map ground points around the stem base region.

    Parameters
    ----------
    perc : :class:`~.perception.Perception` with a depth map (its ground mask, tree mask, rope
        and camera are used).
    edges : :class:`~.edges.TrunkEdges` at the rope (the stem's width sets the search window).
    up_hint : (3,) up direction from the pose or the vanishing point, or None: a plane whose
        normal is more than about 45 degrees from it is refused.

    Returns
    -------
    ``(plane, reason)``: :class:`~.fits.PlaneFit` and "", or None and why not.
    """
    depth = perc.depth
    H, W = depth.shape
    g = perc.ground_mask & (depth > 0)
    ys, xs = np.nonzero(g)
    if len(xs) < 50:
        return None, "too few ground pixels"
    c = np.asarray(perc.rope_xy)
    wpx = max(edges.width_px, 4.0)
    # prefer ground within a generous window around and below the stem
    near = (np.abs(xs - c[0]) < max(12 * wpx, 0.25 * W)) & (ys > c[1] - 0.05 * H)
    if near.sum() >= 200:
        xs, ys = xs[near], ys[near]
    if len(xs) > 4000:
        sel = np.random.default_rng(0).choice(len(xs), 4000, replace=False)
        xs, ys = xs[sel], ys[sel]
    z = depth[ys, xs].astype(np.float64)
    nxy = perc.camera.undistort_points(np.c_[xs, ys].astype(np.float64), normalized=True)
    P = np.c_[nxy * z[:, None], z]
    zt = depth_at(depth, perc.tree_mask, c, 3)
    thr = 0.02 * (zt if np.isfinite(zt) else np.median(z)) + 0.01
    pl = fit_plane_ransac(P, threshold=thr)
    if not pl:
        return None, pl.reason
    if up_hint is not None and pl.n @ up_hint < 0.7:
        return None, "ground plane not level"
    return pl, ""
