"""Simulated user taps for evaluation: the stem base (``--base``) and the rope (``--pick``).

``dbh eval --tap-base`` / ``--tap-rope`` and the error model stand in for a user who taps the
photo: the true pixel from a ``dbh synth`` sample's ground truth plus seeded Gaussian noise.

Imported by :mod:`.synth_eval` and :mod:`.error_model`; imports numpy and the scene generator's
``stem_base_pixel`` (the true base pixel) and ``base_in_view``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["true_base_pixel", "simulated_tap", "simulated_rope_tap", "sample_base_tap", "sample_rope_tap"]


def true_base_pixel(meta: dict, depth: np.ndarray | None = None, *, tolerance_m: float = 0.3,
                    clutter_height_m: float | None = None):
    """Where the roped stem meets the ground in the photo: the front contact point.

    Parameters
    ----------
    meta : sample record (``K``, ``dist``, ``R_world_from_cam``, ``t_world_from_cam``, ``trees``).
    depth : (H, W) ground-truth z-depth; when given, the point counts as visible only where the
        depth there is within ``tolerance_m`` of the point's own depth.
    clutter_height_m : when given (with ``depth``), a hidden base that a person still reads
        through clutter lower than this (grass, litter; :func:`monodbh.models.synthetic.base_in_view`)
        gets the status ``"in_clutter"``.

    Returns
    -------
    ``(xy, status)``: xy (2,) photo pixel (None when outside the photo), status ``"visible"``,
    ``"in_clutter"``, ``"occluded"``, ``"outside"`` or ``"no_rope"``.

    Examples
    --------
    >>> xy, status = true_base_pixel(meta, depth)     # doctest: +SKIP
    """
    from monodbh.models.synthetic import stem_base_pixel

    tid = meta.get("roped_tree")
    if not tid:
        return None, "no_rope"
    tree = next(t for t in meta["trees"] if t["id"] == tid)
    xy, status = stem_base_pixel(meta, tree, depth, tolerance_m=tolerance_m)
    if status == "occluded" and clutter_height_m is not None and depth is not None:
        from monodbh.models.synthetic import base_in_view, stem_axis_point_cam

        z = float(stem_axis_point_cam(meta, tree, 0.0)[2])
        width = 2.0 * float(np.asarray(meta["K"], float)[0, 0]) * float(tree["r_bh_m"]) / max(z, 0.05)
        if base_in_view(meta, tree, depth, xy, width, clutter_height_m):
            status = "in_clutter"
    return xy, status



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


def sample_base_tap(stem: Path, meta: dict, noise_px: float, index: int):
    """A simulated stem-base tap on sample ``stem`` (``folder/NNNNNN``; its ``.npz`` read).

    :func:`simulated_tap` on the sample's depth, clipped to the photo's left and top edges
    (``(max(x, 0), max(y, 0))``); None for a scene without rope or a base out of view.
    """
    if not meta.get("roped_tree"):
        return None
    with np.load(Path(stem).with_suffix(".npz")) as z:
        xy = simulated_tap(meta, z["depth"], noise_px, index)
    return None if xy is None else (max(xy[0], 0.0), max(xy[1], 0.0))


def sample_rope_tap(stem: Path, meta: dict, noise_px: float, index: int):
    """A simulated rope tap on sample ``stem`` (``folder/NNNNNN``; its ``.npz`` read).

    :func:`simulated_rope_tap` on the sample's rope mask; None for a scene without rope or with
    no rope pixel in view.
    """
    if not meta.get("roped_tree"):
        return None
    with np.load(Path(stem).with_suffix(".npz")) as z:
        return simulated_rope_tap(z["rope"], noise_px, index)
