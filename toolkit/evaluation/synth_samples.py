"""The samples of a ``dbh synth`` folder as the evaluation reads them: listing, camera, true values.

A sample ``NNNNNN`` is ``NNNNNN.jpg`` (the photo), ``NNNNNN.json`` (its record: camera ``K``,
``dist``, ``width``, ``height``, pose, ``trees``, ``roped_tree``, ``rope``) and ``NNNNNN.npz``
(ground-truth arrays ``monodbh.models.synthetic.io.GT_KEYS``). The folder is read directly;
only :func:`read_ground_truth` imports the dataset format's module (not the renderer).

Imported by the other evaluation modules and ``monodbh.cli``; imports ``monodbh.calib``, numpy
and ``monodbh.models.synthetic.io``.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Optional

import numpy as np

__all__ = ["list_synth_samples", "camera_from_meta", "read_ground_truth", "gt_dbh_cm", "gt_rope_px",
           "true_rope_diameter_m", "gt_silhouette", "on_true_rope", "WRONG_ROPE_FRACTION"]

#: a measured photo's rope (``rope_xy``) farther than this fraction of the photo's long side from
#: every pixel of the roped tree's true rope is another band: a wrong tree was measured
WRONG_ROPE_FRACTION = 0.012


def list_synth_samples(folder: str | os.PathLike, *, need_npz: bool = False) -> list[int]:
    """Indices of the samples ``NNNNNN.jpg`` + ``NNNNNN.json`` (+ ``.npz``) in ``folder``, sorted."""
    out = []
    for p in Path(folder).glob("[0-9]" * 6 + ".json"):
        if p.with_suffix(".jpg").is_file() and (not need_npz or p.with_suffix(".npz").is_file()):
            out.append(int(p.stem))
    return sorted(out)


def camera_from_meta(meta: dict):
    """The ``monodbh.calib.Camera`` of a synthetic sample (``K``, ``dist``, ``width``, ``height``).

    Parameters
    ----------
    meta : dict
        The sample's record; ``dist`` may be missing (no distortion).

    Returns
    -------
    monodbh.calib.Camera
        Named ``"synthetic"``, for the photo's full size.
    """
    from monodbh.calib import Camera

    return Camera(meta["K"], meta.get("dist"), (int(meta["width"]), int(meta["height"])),
                  name="synthetic")


def read_ground_truth(photo: str | os.PathLike) -> dict:
    """The ground truth of the sample whose photo is ``photo``: the ``.npz`` and ``.json`` beside it.

    Returns
    -------
    dict
        ``monodbh.models.synthetic.io.GT_KEYS`` (``depth`` (H, W) float32 metres, ``semantic`` (H, W) uint8,
        ``instance`` (H, W) int, ``rope`` (H, W) bool, ``z1``/``z2`` (H, W) float32) and
        ``meta`` (the record); no ``rgb`` (the caller reads the photo as it is measured).

    Raises
    ------
    OSError, ValueError, KeyError
        A missing or unreadable file or array.
    """
    from monodbh.models.synthetic.io import GT_KEYS, OPTIONAL_GT_KEYS

    stem = Path(photo).with_suffix("")
    out: dict = {}
    with np.load(stem.with_suffix(".npz")) as z:
        for k in GT_KEYS:
            if k in z.files or k not in OPTIONAL_GT_KEYS:
                out[k] = z[k]
    out["meta"] = json.loads(stem.with_suffix(".json").read_text())
    return out


def gt_dbh_cm(meta: dict) -> Optional[float]:
    """Ground-truth DBH (cm) of the roped tree, or None for a scene without rope."""
    k = meta.get("roped_tree")
    if not k:
        return None
    return float(meta["trees"][int(k) - 1]["dbh_m"]) * 100.0


def gt_silhouette(meta: dict, n: int = 4096) -> Optional[tuple[float, float]]:
    """``(silhouette diameter m, distance m)`` of the roped stem at 1.3 m as this camera sees it.

    The stem's cross-section (the generator's ellipse and harmonics, taper and flare) is sampled
    at ``n`` angles; its angular width ``alpha`` is taken between the two extreme tangent rays
    in the plane across the stem axis, and the silhouette diameter is that of the round stem
    showing the same width, ``2 Zp sin(alpha / 2)`` (``Zp``: the camera's distance to the axis,
    across it). ``distance`` is the true axis point's ``hypot(x, z)`` in camera coordinates,
    the pipeline's definition of ``distance_m``. A single view cannot do better than this
    diameter: it differs from the tape DBH by the stem's out-of-roundness. None without a roped
    tree or without the record's fields.
    """
    from monodbh.models.synthetic.scene import BREAST_HEIGHT_M, cross_section_shape, stem_radius_scale

    tree = next((t for t in meta.get("trees", []) if t.get("id") == meta.get("roped_tree")), None)
    try:
        C = np.asarray(meta["t_world_from_cam"], np.float64)
        ax = np.asarray(tree["axis_world"], np.float64)
        e1, e2 = np.asarray(tree["e1_world"], np.float64), np.asarray(tree["e2_world"], np.float64)
        A = np.asarray(tree["position_world"], np.float64) + BREAST_HEIGHT_M * ax
        th = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
        r = cross_section_shape(th, float(tree["axis_ratio"]), float(tree["ellipse_phase_rad"]),
                                tree.get("harmonics", []))
        r = r * float(stem_radius_scale(BREAST_HEIGHT_M, float(tree["r_bh_m"]), float(tree.get("taper", 0.0)),
                                        float(tree.get("flare", 0.0)), float(tree.get("height_m", 1e3))))
        pc = np.asarray(tree["bh_point_cam"], np.float64)
    except (TypeError, KeyError, ValueError):
        return None
    P = A[None] + (r * np.cos(th))[:, None] * e1[None] + (r * np.sin(th))[:, None] * e2[None]
    w = A - C
    w = w - (w @ ax) * ax
    zp = float(np.linalg.norm(w))
    w = w / zp
    u = np.cross(ax, w)
    V = P - C
    phi = np.arctan2(V @ u, V @ w)
    alpha = float(phi.max() - phi.min())
    return 2.0 * zp * np.sin(alpha / 2.0), float(np.hypot(pc[0], pc[2]))


def gt_rope_px(meta: dict) -> Optional[float]:
    """The roped tree's rope thickness in photo pixels, ``fx D / z`` (``z`` the stem's front at 1.3 m).

    None for a scene without rope or a record without the rope's diameter. The rope detector's
    working range starts at about 1 px (1-2 px ropes at 10 m); ``dbh eval`` reports the detection
    rate per thickness bin (``synth_eval.ROPE_PX_BINS``).
    """
    k = meta.get("roped_tree")
    rope = meta.get("rope") or {}
    try:
        tree = next(t for t in meta["trees"] if t["id"] == k)
        z = float(tree["bh_point_cam"][2]) - float(tree["r_bh_m"])
        d = float(rope.get("marker_width_m", rope["tube_diameter_m"]))     # a strap: its width
        return float(meta["K"][0][0]) * d / z if z > 0 else None
    except (KeyError, StopIteration, TypeError, ValueError, IndexError):
        return None


def true_rope_diameter_m(meta: dict) -> float | None:
    """The rope's true diameter (m) in a sample record, as a user gives it with ``dbh measure
    --rope-mm`` (``dbh eval --rope-known``); None for a scene without rope."""
    rope = meta.get("rope") or {}
    d = rope.get("marker_width_m", rope.get("tube_diameter_m"))      # a strap's width, a rope's diameter
    return None if d is None else float(d)


def on_true_rope(stem: Path, meta: dict, rope_xy) -> Optional[bool]:
    """Does the reported rope centre ``rope_xy`` (photo pixels) lie on the roped tree's true rope?

    Within :data:`WRONG_ROPE_FRACTION` of the photo's long side of a true rope pixel. None when
    the sample has no rope, no reported rope or no ``.npz`` ground truth.
    """
    k = meta.get("roped_tree")
    npz = Path(stem).with_suffix(".npz")
    if not k or rope_xy is None or not npz.is_file():
        return None
    with np.load(npz) as z:
        ys, xs = np.nonzero(z["rope"] & (z["instance"] == k))
    if not len(xs):
        return None
    tol = WRONG_ROPE_FRACTION * max(int(meta["width"]), int(meta["height"]))
    return bool(np.min(np.hypot(xs - float(rope_xy[0]), ys - float(rope_xy[1]))) <= tol)
