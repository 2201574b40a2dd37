"""The DBH estimators at the scale found: the tangent rays, the tree network's circle, and their combination.

Imported by :mod:`.measure`; imports :mod:`.fits` and :mod:`.sigma`. ``tangent`` is
``2 D sin(alpha / 2)`` from the edges' tangent rays; ``cloud`` is a circle fitted (RANSAC and a
geometric refinement) to the front and back surface points of the stem slice at the rope (the
silhouette depth maps). With network perception the circle only checks the tangent estimate
(``DbhConfig.circle_check_only``); with ground-truth perception the two are combined by
inverse-variance weighting, with a 1-sigma that includes the single-view ovality term (decision
record ``docs/decisions/scale-combination.md``).
"""
from __future__ import annotations

import numpy as np

from ..result import MeasureResult
from .config import DbhConfig, GeometryConfig
from .edges import TrunkEdges
from .fits import CircleFit, fit_circle, normalize, pixel_rays, project_perpendicular, tangent_diameter
from .perception import Perception
from .sigma import SigmaTables
from .up import StemAxis

__all__ = ["tangent_estimate", "slice_circle", "cloud_estimate", "combine_estimates", "estimate_dbh"]


def tangent_estimate(axis: StemAxis, edges: TrunkEdges, A: np.ndarray, tables: SigmaTables) -> tuple[float, float, float]:
    """``(diameter (m), relative sigma, edge term)`` from the tangent rays at the axis point ``A``
    (3,); the edge term (the edges' pixel noise over the stem's width) is shared with the circle."""
    d_tan = tangent_diameter(axis.r_L, axis.r_R, axis.v, A)
    sm, sn = tables.model, tables.network
    edge_rel = np.hypot(sm["edge_px"], edges.edge_rms_px) * np.sqrt(2) / max(edges.width_px, 1.0)
    sig = np.sqrt(sm["ovality"] ** 2 + edge_rel ** 2 + (sn["width"] ** 2 if tables.net else 0.0))
    return d_tan, sig, edge_rel


def slice_circle(perc: Perception, edges: TrunkEdges, A: np.ndarray, v: np.ndarray) -> tuple[CircleFit, np.ndarray | None]:
    """Front/back points of the stem slice at the rope -> circle in the cross-section plane.

    The slice's points are read from the silhouette depth maps (``perc.silhouette_fn`` at the
    axis depth ``A[2]``, else ``perc.z1``, ``perc.z2``, metres) on four lines across the stem
    above and below the rope. Returns the :class:`~.fits.CircleFit` (falsy with a reason) and
    the points (N, 2) in the cross-section plane (None when there are none).
    """
    cam = perc.camera
    if perc.silhouette_fn is not None:
        z1, z2 = perc.silhouette_fn(float(A[2]), edges)
    else:
        z1, z2 = perc.z1, perc.z2            # metric (ground truth)
    if z1 is None:
        return CircleFit(reason="no silhouette"), None
    pts = []
    u = edges.across
    w = edges.width_px
    for t in (-3, -2, 2, 3):
        base = 0.5 * (edges.left_xy + edges.right_xy) + t * max(1.0, 1.5 * perc.rope_half_px) * edges.along
        for f in np.linspace(-0.5, 0.5, max(9, int(w))):
            p = base + f * w * u
            x, y = int(round(p[0])), int(round(p[1]))
            if not (0 <= y < z1.shape[0] and 0 <= x < z1.shape[1]):
                continue
            if not perc.tree_mask[y, x] or z1[y, x] <= 0:
                continue
            pts.append((p[0], p[1], z1[y, x], z2[y, x]))
    if len(pts) < 6:
        return CircleFit(reason="too few slice points"), None
    P = np.array(pts)
    nxy = cam.undistort_points(P[:, :2], normalized=True)
    front = np.c_[nxy * P[:, 2:3], P[:, 2]]
    back = np.c_[nxy * P[:, 3:4], P[:, 3]]
    X = np.concatenate([front, back[P[:, 3] > P[:, 2] + 1e-4]])
    e1 = normalize(project_perpendicular(A, v))
    e2 = np.cross(v, e1)
    uv = np.c_[X @ e2, X @ e1]
    rmax = 2.0 * np.linalg.norm(A) * np.sin(0.5 * np.arccos(np.clip(
        normalize(project_perpendicular(pixel_rays(cam, edges.left_xy[None])[0], v)) @
        normalize(project_perpendicular(pixel_rays(cam, edges.right_xy[None])[0], v)), -1, 1))) + 0.05
    thr = max(0.003, 0.03 * rmax)
    return fit_circle(uv, threshold=thr, r_max=rmax), uv


def cloud_estimate(perc: Perception, edges: TrunkEdges, axis: StemAxis, A: np.ndarray, edge_rel: float,
                   tables: SigmaTables, res: MeasureResult, flags: list[str],
                   config: DbhConfig | None = None) -> tuple[float, float] | None:
    """``(diameter (m), relative sigma)`` of the slice's circle (:func:`slice_circle`), or None
    where it fails; flags ``short_arc`` and ``low_inlier_ratio``; the slice points and circle go
    to ``res.debug`` (``slice_uv``, ``circle``)."""
    cfg = config or DbhConfig()
    cloud_fit, slice_uv = slice_circle(perc, edges, A, axis.v)
    if not cloud_fit:
        return None
    sm = tables.model
    arc_pen = 0.02 * max(0.0, (300 - cloud_fit.arc_deg) / 120)
    sig = np.sqrt(sm["ovality"] ** 2 * 0.5 + sm["cloud_extra"] ** 2 + arc_pen ** 2
                  + edge_rel ** 2 + (tables.network["cloud"] ** 2 if tables.net else 0.0))
    res.debug["slice_uv"] = slice_uv
    res.debug["circle"] = (cloud_fit.xc, cloud_fit.yc, cloud_fit.r)
    if cloud_fit.arc_deg < cfg.short_arc_deg:
        flags.append("short_arc")
    if cloud_fit.inlier_ratio < cfg.min_inlier_ratio:
        flags.append("low_inlier_ratio")
    return 2 * cloud_fit.r, sig


def combine_estimates(est: dict[str, float], sig: dict[str, float], *, circle_as_check: bool, flags: list[str],
                      config: DbhConfig | None = None) -> tuple[float, float, dict[str, float]]:
    """``(diameter (m), relative sigma, estimates)``: the inverse-variance mean of ``est`` (the
    tangent estimate alone with ``circle_as_check``: the circle then only flags
    ``estimators_disagree``), at least half the two estimators' spread; ``estimates`` are all
    of ``est``. Flags ``circle_as_check`` and ``estimators_disagree``."""
    cfg = config or DbhConfig()
    est_all = est
    if circle_as_check and "cloud" in est:
        flags.append("circle_as_check")
        if abs(np.log(est["cloud"] / est["tangent"])) > cfg.disagree_sigmas * np.hypot(sig["tangent"], sig["cloud"]):
            flags.append("estimators_disagree")
        est_all = dict(est)
        est = {"tangent": est["tangent"]}
    ws = {k: 1 / sig[k] ** 2 for k in est}
    d = sum(ws[k] * est[k] for k in est) / sum(ws.values())
    rel_sig_est = 1 / np.sqrt(sum(ws.values()))
    if len(est) > 1:
        spread = abs(est["tangent"] - est["cloud"]) / d
        if spread > cfg.disagree_sigmas * np.hypot(sig["tangent"], sig["cloud"]):
            flags.append("estimators_disagree")
        rel_sig_est = max(rel_sig_est, spread / 2)
    return d, rel_sig_est, est_all


def estimate_dbh(perc: Perception, edges: TrunkEdges, axis: StemAxis, A: np.ndarray, *, leader: str,
                 scale_sigma: float, width_vs_rope: float, tables: SigmaTables, res: MeasureResult,
                 flags: list[str], config: GeometryConfig | None = None) -> None:
    """The DBH at the axis point ``A`` (3,) (the scale's ``leader`` and relative ``scale_sigma``):
    sets ``res.dbh_cm``, ``res.dbh_sigma_cm`` and ``res.estimates_cm``; ``width_vs_rope`` (the
    edges' disagreement with the rope band, shared by both estimators) widens the sigma. Flags
    ``few_pixels_across_stem`` for a narrow stem."""
    cfg = config or GeometryConfig()
    est, sig = {}, {}
    est["tangent"], sig["tangent"], edge_rel = tangent_estimate(axis, edges, A, tables)
    if perc.z1 is not None or perc.silhouette_fn is not None:
        cloud = cloud_estimate(perc, edges, axis, A, edge_rel, tables, res, flags, cfg.dbh)
        if cloud is not None:
            est["cloud"], sig["cloud"] = cloud
    # with network perception the tree network's circle only checks the tangent estimate (or,
    # with ``circle_check_only`` off, where a precise scale leads)
    circle_as_check = tables.net and (cfg.dbh.circle_check_only or leader in cfg.scale.precise_sources)
    d, rel_sig_est, est_all = combine_estimates(est, sig, circle_as_check=circle_as_check, flags=flags,
                                                config=cfg.dbh)
    # edges that disagree with the rope band's length are shared by both estimators (the slice
    # lies between them): the gap widens the uncertainty of the combination
    rel_sig_est = float(np.hypot(rel_sig_est, width_vs_rope))
    rel_sig = np.hypot(rel_sig_est, scale_sigma)
    res.dbh_cm = 100 * d
    res.dbh_sigma_cm = 100 * d * rel_sig
    res.estimates_cm = {k: 100 * v_ for k, v_ in est_all.items()}
    if edges.width_px < cfg.dbh.few_pixels_px:
        flags.append("few_pixels_across_stem")
