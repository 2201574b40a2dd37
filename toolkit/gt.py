"""Ground-truth perception from a ``dbh synth`` sample (the single-view floor of ``dbh eval``).

Feeds the same geometry as the networks (:func:`~.measure_core.measure_from_perception`)
with exact masks, depth and silhouette depth maps, so the difference between the two runs is
what perception costs.
"""
from __future__ import annotations

import numpy as np

from .geometry import Perception

__all__ = ["perception_from_ground_truth", "true_base_pixel", "simulated_tap", "simulated_rope_tap", "true_rope_diameter_m"]


def true_base_pixel(meta: dict, depth: np.ndarray | None = None, *, tolerance_m: float = 0.3):
    """Where the roped stem meets the ground in the photo: the front contact point.

    Parameters
    ----------
    meta : sample record (``K``, ``dist``, ``R_world_from_cam``, ``t_world_from_cam``, ``trees``).
    depth : (H, W) ground-truth z-depth; when given, the point counts as visible only where the
        depth there is within ``tolerance_m`` of the point's own depth.

    Returns
    -------
    ``(xy, status)``: xy (2,) photo pixel (None when outside the photo), status ``"visible"``,
    ``"occluded"``, ``"outside"`` or ``"no_rope"``.

    Examples
    --------
    >>> xy, status = true_base_pixel(meta, depth)     # doctest: +SKIP
    """
    from ..models.synthetic import stem_base_pixel
    tid = meta.get("roped_tree")
    if not tid:
        return None, "no_rope"
    tree = next(t for t in meta["trees"] if t["id"] == tid)
    return stem_base_pixel(meta, tree, depth, tolerance_m=tolerance_m)


def true_rope_diameter_m(meta: dict) -> float | None:
    """The rope's true diameter (m) in a sample record, as a user gives it with ``dbh measure
    --rope-mm`` (``dbh eval --rope-known``); None for a scene without rope."""
    d = (meta.get("rope") or {}).get("tube_diameter_m")
    return None if d is None else float(d)


def simulated_tap(meta: dict, depth: np.ndarray, noise_px: float, seed: int):
    """A user's tap on the stem base (``dbh measure --base``), simulated for evaluation: the
    true base pixel plus Gaussian noise of ``noise_px`` per axis (seeded by ``seed``) when the
    base is visible, else None.

    Returns
    -------
    ``(x, y)`` floats or None.
    """
    xy, status = true_base_pixel(meta, depth)
    if status != "visible":
        return None
    xy = xy + np.random.default_rng(seed).normal(0.0, noise_px, 2)
    return float(xy[0]), float(xy[1])


def simulated_rope_tap(rope: np.ndarray, noise_px: float, seed: int):
    """A user's tap on the rope (``dbh measure --pick``), simulated for evaluation: the rope's
    visible pixel (``rope`` ``(H, W)`` bool, the sample's mask) nearest the median of them all (a
    person taps on the rope, and a near rope is an arc whose median point lies off it) plus
    Gaussian noise of ``noise_px`` per axis (seeded by ``seed``), or None when none is visible.

    Examples
    --------
    >>> m = np.zeros((50, 80), bool); m[20, 10:31] = True
    >>> simulated_rope_tap(m, 0.0, 0)
    (20.0, 20.0)
    """
    ys, xs = np.nonzero(np.asarray(rope, bool))
    if not len(xs):
        return None
    mx, my = np.median(xs), np.median(ys)
    k = int(np.argmin((xs - mx) ** 2 + (ys - my) ** 2))
    xy = np.array([xs[k], ys[k]], float) + np.random.default_rng([seed, 7]).normal(0.0, noise_px, 2)
    return float(xy[0]), float(xy[1])


def perception_from_ground_truth(sample: dict, camera, *, use_silhouette: bool = True) -> Perception | None:
    """Build :class:`Perception` from a sample dict (``rgb``, ``instance``, ``semantic``,
    ``rope``, ``depth``, ``z1``, ``z2``, ``meta``). Returns None when the scene has no rope."""
    meta = sample["meta"]
    tid = meta.get("roped_tree")
    if not tid:
        return None
    inst = sample["instance"]
    tree = inst == tid
    rope = sample["rope"] & tree
    ys, xs = np.nonzero(rope)
    if len(xs) < 3:
        return None
    P = np.c_[xs, ys].astype(np.float64)
    c = np.median(P, 0)
    # band direction: principal axis of the rope pixels
    w, V = np.linalg.eigh(np.cov((P - c).T))
    d = V[:, -1]
    rope_meta = meta.get("rope") or {}
    tree_meta = meta["trees"][tid - 1]
    if "center_world" in rope_meta and "axis_world" in tree_meta:
        # exact: project the stem axis point at 1.3 m and the axis direction
        import cv2
        R = np.asarray(meta["R_world_from_cam"])
        t = np.asarray(meta["t_world_from_cam"])
        A = np.asarray(rope_meta["center_world"])
        ax = np.asarray(tree_meta["axis_world"])
        pc = (np.stack([A, A + 0.1 * ax]) - t) @ R
        uv, _ = cv2.projectPoints(pc, np.zeros(3), np.zeros(3), np.asarray(meta["K"], float),
                                  np.asarray(meta["dist"], float))
        uv = uv.reshape(2, 2)
        along = uv[1] - uv[0]
        along /= np.linalg.norm(along) + 1e-12
        c = uv[0]
        d = np.array([-along[1], along[0]])
    # thickness from the tube diameter and the stem distance
    if rope_meta.get("tube_diameter_m") and "bh_point_cam" in tree_meta:
        half = 0.5 * rope_meta["tube_diameter_m"] * float(meta["K"][0][0]) / max(tree_meta["bh_point_cam"][2], 0.1)
        half = max(0.5, half)
    else:
        length = max(1.0, 4 * np.sqrt(max(w[-1], 1e-9)))
        half = max(0.5, 0.5 * len(xs) / length)
    # put the centre on the stem mid-line: middle of the tree run along the band through c
    s = np.arange(-2000, 2000, 0.5)
    q = c[None] + s[:, None] * d[None]
    ok = (q[:, 0] >= 0) & (q[:, 0] <= tree.shape[1] - 1) & (q[:, 1] >= 0) & (q[:, 1] <= tree.shape[0] - 1)
    inside = np.zeros(len(s), bool)
    qi = np.round(q[ok]).astype(int)
    inside[ok] = tree[qi[:, 1], qi[:, 0]]
    i0 = int(np.argmin(np.abs(s)))
    if inside[i0]:
        lo = hi = i0
        while lo > 0 and inside[lo - 1]:
            lo -= 1
        while hi < len(s) - 1 and inside[hi + 1]:
            hi += 1
        c = c + 0.5 * (s[lo] + s[hi]) * d
    return Perception(
        rgb=sample["rgb"], camera=camera, rope_xy=c, rope_dir=d, rope_half_px=float(min(half, 6.0)),
        tree_mask=tree, ground_mask=sample["semantic"] == 1, depth=sample["depth"], depth_is_metric=True,
        z1=sample["z1"] if use_silhouette else None, z2=sample["z2"] if use_silhouette else None,
        source="ground_truth")
