"""From perception (rope, stem mask, ground, depth, silhouette depth) to a metric DBH: :func:`measure_from_perception`.

Imported by the measuring pipeline (:mod:`monodbh.toolkit.pipeline`) and by ground-truth
evaluation; imports the stages of :mod:`monodbh.toolkit.geometry`. Pure geometry on numpy
arrays: the same code runs on network outputs and on ground-truth perception (``dbh eval
--gt-perception``, the single-view floor), so the two are directly comparable.

The stages (see docs/METHOD.md, "How the scale is set"):

1. the stem's silhouette edges at the rope, checked against the rope band (:mod:`.stem_edges`);
2. the up direction (:mod:`.up`: calibrated pose, vertical vanishing point, the depth map's
   ground plane (:mod:`.ground`), the image's vertical) and the stem's direction and axis ray;
3. the stem base (:mod:`.stem_base`: the user's tap, the stem-base network, the edge tracker);
4. the scale candidates and their combination (:mod:`.scale`);
5. the DBH estimators (:mod:`.dbh`).
"""
from __future__ import annotations

import time

import numpy as np

from ..result import MeasureResult
from .config import GeometryConfig
from .dbh import estimate_dbh
from .edges import TrunkEdges, channel_mean
from .fits import PlaneFit, project_perpendicular
from .ground import ground_plane
from .perception import Perception
from .scale import choose_scale, scale_candidates
from .sigma import sigma_tables
from .stem_base import find_stem_base, visible_stem_bound
from .stem_edges import stem_edges
from .up import choose_up, photo_up_sources, stem_axis, vertical_hint

__all__ = ["measure_from_perception"]


def _take_depth(perc: Perception, res: MeasureResult) -> None:
    """``perc.depth`` from ``perc.depth_job`` (computed on another thread) where it is not there
    yet; the wait goes to ``res.timings_ms["depth"]``."""
    if perc.depth is None and perc.depth_job is not None:
        t_w = time.perf_counter()
        perc.depth = perc.depth_job.result()
        res.timings_ms["depth"] = res.timings_ms.get("depth", 0.0) + 1000 * (time.perf_counter() - t_w)


def _ground_up(perc: Perception, edges: TrunkEdges, up_sources: dict, flags: list[str]) -> PlaneFit | None:
    """The depth map's ground plane (None without depth or fit, flagged ``no_ground_plane``
    then); its normal joins ``up_sources`` as ``ground_plane``."""
    if perc.depth is None:
        return None
    plane, _ = ground_plane(perc, edges, vertical_hint(up_sources))
    if plane is not None:
        up_sources["ground_plane"] = plane.n
    else:
        flags.append("no_ground_plane")
    return plane


def measure_from_perception(perc: Perception, photo: str = "", *, timings: dict | None = None,
                            config: GeometryConfig | None = None) -> MeasureResult:
    """Measure the DBH of the roped stem from :class:`~.perception.Perception`.

    Parameters
    ----------
    perc : the perception (its ``depth`` is set from ``depth_job`` where first needed).
    photo : the photo's name in the result.
    timings : the stage times so far (ms), copied into the result's ``timings_ms``; this adds
        ``vanishing``, ``depth`` (the wait for the depth map), ``base`` and ``geometry``.
    config : :class:`~.config.GeometryConfig` (the defaults when None).

    Returns
    -------
    MeasureResult with ``dbh_cm``/``dbh_sigma_cm``/``distance_m``/``scale_source``/``flags``
    and ``estimates_cm``; ``error`` set (and ``dbh_cm`` None) when the stem cannot be measured.
    ``debug`` holds the intermediate geometry (edges, axis, scale candidates, ...).
    """
    cfg = config or GeometryConfig()
    t0 = time.perf_counter()
    res = MeasureResult(photo=photo, timings_ms=dict(timings or {}))
    cam = perc.camera
    gray = channel_mean(perc.rgb)
    tables = sigma_tables(perc, cfg.sigma)
    edges, flags, width_vs_rope = stem_edges(perc, gray, cfg.stem_edges, cfg.edges)
    if not edges:
        res.error = f"cannot measure the roped stem: {edges.reason}"
        return res
    res.rope_xy = [float(perc.rope_xy[0]), float(perc.rope_xy[1])]
    up_sources = photo_up_sources(perc, gray, res, cfg.vanishing)
    _take_depth(perc, res)
    plane = _ground_up(perc, edges, up_sources, flags)
    axis = stem_axis(cam, edges, choose_up(up_sources, flags, res, cfg.up))
    base = find_stem_base(perc, gray, edges, axis, up_sources, res, flags, cfg.stem_base, cfg.up)
    bound = visible_stem_bound(cam, axis, base)
    if bound is not None:
        res.debug["scale_bound"] = bound
    cands = scale_candidates(perc, edges, axis, base, plane, up_sources, tables, flags, cfg)
    if not cands:
        res.error = "cannot set the metric scale: no stem base, ground plane, pose or depth"
        return res
    res.debug["stem_width_px"] = float(edges.width_px)
    res.debug["fx_px"] = float(np.asarray(cam.K, float)[0, 0])
    scale = choose_scale(perc, cands, bound, res, flags, cfg.scale)
    A = scale.lam * axis.r_A
    res.distance_m = float(np.linalg.norm(A[[0, 2]]))   # horizontal-ish distance camera -> stem axis
    estimate_dbh(perc, edges, axis, A, leader=scale.leader, scale_sigma=scale.sig_rel, width_vs_rope=width_vs_rope,
                 tables=tables, res=res, flags=flags, config=cfg)
    res.flags = flags
    res.debug.update(dict(edges=edges, edges_xy=np.stack([edges.left_xy, edges.right_xy]), axis_dir=axis.v,
                          axis_point=A, scale_candidates=cands,
                          D_axis=float(np.linalg.norm(project_perpendicular(A, axis.v))),
                          base_xy=base.xy, rope_xy=np.asarray(perc.rope_xy)))
    res.timings_ms["geometry"] = 1000 * (time.perf_counter() - t0)
    return res
