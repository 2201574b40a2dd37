"""Ground-truth perception from a ``dbh synth`` sample (the single-view floor of ``dbh eval``).

Feeds the same geometry as the networks (``geometry.measure_from_perception``) with exact
masks, depth and silhouette depth maps, so the difference between the two runs is what
perception costs. :func:`measure_photo_gt` is the measure function of ``dbh eval
--gt-perception`` (:data:`GT_MEASURE`, run through ``toolkit.batch`` like the pipeline's): it
needs no networks and no session.

Imported by ``monodbh.cli`` (through :data:`GT_MEASURE`) and the evaluation tools; imports
``monodbh.calib``, ``toolkit.geometry`` and :mod:`.synth_samples`.
"""
from __future__ import annotations

import time

import numpy as np

from monodbh.calib.errors import MonodbhError
from monodbh.toolkit.geometry import Perception, measure_from_perception
from monodbh.toolkit.result import MeasureResult

__all__ = ["perception_from_ground_truth", "measure_photo_gt", "GT_MEASURE"]

#: ``"module:function"`` of :func:`measure_photo_gt`, for ``toolkit.batch.Backend``
GT_MEASURE = "monodbh.toolkit.evaluation.ground_truth:measure_photo_gt"


def measure_photo_gt(path: str, camera, *, session=None, **_ignored) -> MeasureResult:
    """Measure a ``dbh synth`` photo from its ground-truth perception (``dbh eval --gt-perception``).

    Reads the sample's ground truth beside the photo (:func:`.synth_samples.read_ground_truth`),
    then the photo itself, and runs ``measure_from_perception`` on
    :func:`perception_from_ground_truth` of them.

    Parameters
    ----------
    path : str
        ``NNNNNN.jpg`` of a ``dbh synth`` folder (``NNNNNN.npz`` and ``.json`` beside it).
    camera : monodbh.calib.Camera
        The sample's camera (adapted to the photo's size here).
    session : object, optional
        Ignored (no networks run); accepted like the pipeline's measure function.
    **_ignored
        The other arguments ``toolkit.batch`` passes a measure function (``pick_xy``,
        ``want_cloud``, ``want_debug``, ``base_xy``, ``rope_diameter_m``): ground truth decides.

    Returns
    -------
    MeasureResult
        ``error`` set for a photo that cannot be measured. ``timings_ms["total"]`` is the time
        from reading the photo on (the ground truth's reading is not timed).

    Raises
    ------
    OSError, ValueError, KeyError
        The sample's ground truth cannot be read (``toolkit.batch`` reports it as the row's
        internal error).
    """
    from monodbh.calib import load_photo

    from .synth_samples import read_ground_truth

    sample = read_ground_truth(path)
    tm: dict = {}
    t0 = time.perf_counter()
    try:
        rgb = load_photo(path)
    except MonodbhError as e:
        return _timed(MeasureResult(photo=str(path), error=str(e)), t0)
    tm["load"] = 1000 * (time.perf_counter() - t0)
    try:
        H, W = rgb.shape[:2]
        cam = camera.for_image(W, H)
        sample["rgb"] = rgb
        perc = perception_from_ground_truth(sample, cam)
        if perc is None:
            res = MeasureResult(photo=str(path), error=f"{path}: no rope found (ground truth has none)",
                                timings_ms=tm)
        else:
            res = measure_from_perception(perc, str(path), timings=tm)
    except MonodbhError as e:
        res = MeasureResult(photo=str(path), error=str(e), timings_ms=tm)
    return _timed(res, t0)


def _timed(res: MeasureResult, t0: float) -> MeasureResult:
    """``res`` with ``timings_ms["total"]`` the milliseconds since ``t0`` (unless it has one)."""
    res.timings_ms = dict(res.timings_ms or {})
    res.timings_ms.setdefault("total", (time.perf_counter() - t0) * 1000.0)
    return res


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
