"""Procedural synthetic forest scenes with exact ground truth (training and evaluation data).

Training-only: needs the ``synth`` extra (trimesh/embreex). Never imported by the measuring
path. See ``docs/ARCHITECTURE.md`` for the sample format.

Examples
--------
>>> from monodbh.models.synthetic import generate_sample
>>> s = generate_sample(seed=0, index=3, size=(320, 240))   # doctest: +SKIP
>>> s["rgb"].shape, s["depth"].dtype, s["meta"]["trees"][0]["dbh_m"]  # doctest: +SKIP
"""
from __future__ import annotations

import numpy as np

from .scene import BREAST_HEIGHT_M, Scene, sample_scene

__all__ = ["generate_sample", "iter_samples", "sample_seed", "scene_meta", "stem_base_pixel", "base_in_view",
           "stem_axis_point_cam", "BREAST_HEIGHT_M"]


def sample_seed(seed: int, index: int) -> int:
    """Independent 63-bit seed of sample ``index`` in the dataset of base ``seed``."""
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(2, np.uint64)[0] >> np.uint64(1))


def stem_base_pixel(meta: dict, tree: dict, depth: np.ndarray | None = None, *, tolerance_m: float = 0.3):
    """Where a stem of a sample record meets the ground in its photo: the front contact point.

    Parameters
    ----------
    meta : sample record (``K``, ``dist``, ``R_world_from_cam``, ``t_world_from_cam``, ``width``,
        ``height``).
    tree : one entry of ``meta["trees"]`` (``position_world``, ``r_bh_m``).
    depth : (H, W) ground-truth z-depth; when given, the point counts as visible only where the
        depth there is within ``tolerance_m`` of the point's own depth.

    Returns
    -------
    ``(xy, status)``: xy (2,) photo pixel (through the record's lens distortion; None when
    outside the photo), status ``"visible"``, ``"occluded"`` or ``"outside"``.
    """
    import cv2
    R = np.asarray(meta["R_world_from_cam"], float)
    t = np.asarray(meta["t_world_from_cam"], float)
    P = np.asarray(tree["position_world"], float).copy()
    toward = t[:2] - P[:2]
    P[:2] += toward / (np.linalg.norm(toward) + 1e-12) * float(tree["r_bh_m"])
    pc = R.T @ (P - t)
    if pc[2] <= 0.05:
        return None, "outside"
    uv, _ = cv2.projectPoints(pc[None], np.zeros(3), np.zeros(3), np.asarray(meta["K"], float),
                              np.asarray(meta.get("dist") or np.zeros(5), float))
    u, v = uv.reshape(2)
    W, H = int(meta["width"]), int(meta["height"])
    if not (0 <= u <= W - 1 and 0 <= v <= H - 1):
        return None, "outside"
    xy = np.array([u, v])
    if depth is not None and abs(float(depth[int(round(v)), int(round(u))]) - pc[2]) > tolerance_m:
        return xy, "occluded"
    return xy, "visible"


def stem_axis_point_cam(meta: dict, tree: dict, height_m: float) -> np.ndarray:
    """Camera-frame point ``(3,)`` of a stem's axis at vertical height ``height_m`` above its base.

    Uses the record's ``R_world_from_cam``, ``t_world_from_cam`` and the tree's
    ``position_world`` (base) and ``axis_world`` (unit direction; vertical if absent).
    """
    base = np.asarray(tree["position_world"], np.float64)
    axis = np.asarray(tree.get("axis_world", (0.0, 0.0, 1.0)), np.float64)
    axis = axis / np.linalg.norm(axis)
    p = base + (height_m / max(axis[2], 0.2)) * axis
    R = np.asarray(meta["R_world_from_cam"], np.float64)
    t = np.asarray(meta["t_world_from_cam"], np.float64)
    return R.T @ (p - t)


def base_in_view(meta: dict, tree: dict, depth: np.ndarray, base_xy, width_px: float,
                 clutter_height_m: float = 0.3) -> bool:
    """Whether a person sees where a stem meets the ground, grass tufts and leaf litter included.

    Parameters
    ----------
    meta, tree : sample record and one of its ``trees`` (as :func:`stem_base_pixel`).
    depth : (H, W) ground-truth z-depth (m).
    base_xy : (2,) the stem's front ground contact in the photo (:func:`stem_base_pixel`).
    width_px : the stem's width in the photo near the ground (pixels).
    clutter_height_m : clutter lower than this (m) does not hide the base.

    Returns
    -------
    True where the base is seen across the stem's front half (its centre and a quarter of
    ``width_px`` to each side not hidden by anything nearer than the stem's radius, at least
    0.3 m), or where the stem's front is seen across its front half at two heights 5 cm apart up
    to ``clutter_height_m`` above the ground (the foot is then read through the clutter; gaps
    in a bush's foliage do not count). A bush that hides the stem higher up hides the base.

    Examples
    --------
    >>> xy, status = stem_base_pixel(meta, tree, depth)               # doctest: +SKIP
    >>> base_in_view(meta, tree, depth, xy, 40.0)                     # doctest: +SKIP
    True
    """
    import cv2
    H, W = depth.shape
    bxy = np.asarray(base_xy, np.float64).reshape(2)
    if not (0 <= bxy[0] <= W - 1 and 0 <= bxy[1] <= H - 1):
        return False
    K = np.asarray(meta["K"], float)
    dist = np.asarray(meta.get("dist") or np.zeros(5), float)

    def project(pc):
        uv, _ = cv2.projectPoints(pc[None], np.zeros(3), np.zeros(3), K, dist)
        return uv.reshape(2)

    def depth_at(p):
        x, y = int(round(p[0])), int(round(p[1]))
        return float(depth[y, x]) if (0 <= x < W and 0 <= y < H) else -1.0

    r = float(tree["r_bh_m"])          # (the radius at 1.3 m; the flare is left out)
    p0, p1 = stem_axis_point_cam(meta, tree, 0.0), stem_axis_point_cam(meta, tree, 0.5)
    if p0[2] <= 0.3 or p1[2] <= 0.3:
        return False
    a = project(p1) - project(p0)
    a = a / (np.linalg.norm(a) + 1e-12)
    u = np.array([a[1], -a[0]])                     # across the stem in the photo
    tol = max(0.3, 0.5 * r + 0.1)
    z0 = depth_at(bxy)
    if abs(z0 - (p0[2] - r)) <= tol and all(depth_at(bxy + f * width_px * u) >= z0 - max(0.3, r)
                                            for f in (-0.25, 0.25)):
        return True
    seen_below = False
    for h in np.arange(0.05, clutter_height_m + 0.05 + 1e-6, 0.05):
        pc = stem_axis_point_cam(meta, tree, float(h))
        if pc[2] <= 0.3:
            return False
        c = project(pc)
        seen = all(abs(depth_at(c + f * width_px * u) - (pc[2] - r)) <= tol for f in (-0.25, 0.0, 0.25))
        if seen and seen_below:
            return True
        seen_below = seen and h <= clutter_height_m + 1e-6
    return False


def scene_meta(scene: Scene, out: dict) -> dict:
    """JSON-serialisable record of a rendered scene (see ``docs/ARCHITECTURE.md``)."""
    cam = scene.camera
    inst = out["instance"]
    counts = np.bincount(inst.ravel(), minlength=len(scene.trees) + 1)
    trees = []
    for t in scene.trees:
        pbh = t.axis_point(BREAST_HEIGHT_M)
        pc = cam.R_wc.T @ (pbh - cam.t_wc)
        trees.append(dict(
            id=t.id, species=t.species, dbh_m=t.dbh_m(), dbh_polygon_m=t.dbh_m(segments=t.segments()),
            axis_ratio=t.axis_ratio, ellipse_phase_rad=t.ell_phase, r_bh_m=t.r_bh,
            position_world=t.base.tolist(), axis_world=t.axis.tolist(), e1_world=t.e1.tolist(),
            e2_world=t.e2.tolist(), height_m=t.height_m, lean_deg=float(np.degrees(np.arccos(t.axis[2]))),
            bh_point_cam=pc.tolist(), distance_m=float(np.hypot(*(pbh[:2] - cam.t_wc[:2]))),
            pixels=int(counts[t.id]), lod=t.lod, dead=t.dead,
            harmonics=t.harmonics.tolist(), flare=t.flare, taper=t.taper,
            rings=[dict(height_m=r.s_m, is_rope=r.is_rope, tube_diameter_m=2 * r.tube_radius_m,
                        width_m=r.width_m, rgb=list(r.rgb), knot=r.knot) for r in t.rings],
        ))
    rope = None
    if scene.roped_tree:
        t = scene.trees[scene.roped_tree - 1]
        r = [x for x in t.rings if x.is_rope][0]
        rope = dict(tree=t.id, height_m=r.s_m, tube_diameter_m=2 * r.tube_radius_m,
                    kind="strap" if r.width_m > 0 else "rope",
                    marker_width_m=r.width_m if r.width_m > 0 else 2 * r.tube_radius_m,
                    center_world=t.axis_point(r.s_m).tolist(), rgb=list(r.rgb),
                    pixels=int((out["rope"] & (inst == t.id)).sum()))
    L = scene.light
    return dict(
        seed=scene.seed, width=cam.width, height=cam.height, K=cam.K.tolist(), dist=cam.dist.tolist(),
        cam_height_m=cam.height_m, pitch_deg=cam.pitch_deg, roll_deg=cam.roll_deg, yaw_deg=cam.yaw_deg,
        R_world_from_cam=cam.R_wc.tolist(), t_world_from_cam=cam.t_wc.tolist(),
        ground_z_under_camera_m=float(cam.t_wc[2] - cam.height_m),
        roped_tree=scene.roped_tree, rope=rope, trees=trees, distractors=scene.distractors,
        light=dict(sun_dir=L.sun_dir.tolist(), overcast=L.overcast, fog_m=L.fog_m, exposure=L.exposure),
        render=out["stats"],
    )


def generate_sample(seed: int, index: int = 0, size: tuple[int, int] = (512, 512), *,
                    distortion: bool = True, aa: bool = True, marker: str = "rope", look: str = "default",
                    stand: str = "forest", foot: str = "plain", view: str = "level") -> dict:
    """Render one sample.

    Parameters
    ----------
    seed, index : dataset seed and sample index (the pair fixes the sample exactly).
    size : (W, H) in pixels.
    distortion : render through a camera with radial distortion.
    marker : the 1.3 m marker: ``"rope"`` (a round rope, the default), ``"strap"`` (a flat red
        strap 20-50 mm wide) or ``"mixed"`` (either, half and half); see
        :func:`~.scene.sample_scene`.
    look : ``"default"``, ``"randomized"`` (domain randomisation) or ``"heldout"`` (for evaluation
        only; no training path accepts it): the same scene with another appearance (:mod:`.looks`).
    stand : ``"forest"`` (the default), ``"park"`` or ``"mixed"``; see :func:`~.scene.sample_scene`.
    foot : ``"plain"`` (the default), ``"clutter"`` (grass and a bush at the roped stem's foot)
        or ``"hidden"`` (taller grass, a bush in front of the foot); see :func:`~.scene.sample_scene`.
    view : ``"level"`` (the default), ``"upward"`` (up the trunk into the crown from close by),
        ``"mixed"`` (upward on a third) or ``"protocol"`` (the photo as README's "Taking the photo"
        asks); see :func:`~.scene.sample_scene`.

    Returns
    -------
    dict with ``rgb`` (H, W, 3) uint8, ``jpeg`` bytes, ``depth``, ``semantic``, ``instance``,
    ``rope``, ``z1``, ``z2`` (H, W) and ``meta`` (JSON record).
    """
    from .render import render_scene
    W, H = int(size[0]), int(size[1])
    if W < 16 or H < 16:
        raise ValueError(f"image size {W}x{H} is too small (min 16x16)")
    s = sample_seed(seed, index)
    rng = np.random.default_rng(s)
    scene = sample_scene(rng, W, H, distortion=distortion, seed=s, marker=marker, stand=stand, foot=foot,
                         view=view)
    out = render_scene(scene, rng, look=look)
    out["meta"] = scene_meta(scene, out)
    out["meta"]["look"] = look
    out["meta"]["stand"] = scene.stand
    if foot != "plain":
        out["meta"]["foot"] = foot
    if view != "level":
        out["meta"]["view"] = scene.view
    out["meta"]["dataset_seed"] = int(seed)
    out["meta"]["index"] = int(index)
    out["scene"] = scene
    return out


def iter_samples(seed: int, count: int | None = None, size: tuple[int, int] = (512, 512), *,
                 start: int = 0, distortion: bool = True, **kw):
    """Yield ``count`` samples (forever if ``None``) of dataset ``seed`` from index ``start``."""
    i = start
    while count is None or i < start + count:
        yield generate_sample(seed, i, size, distortion=distortion, **kw)
        i += 1
