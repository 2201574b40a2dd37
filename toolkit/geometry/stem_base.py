"""Where the roped stem meets the ground: the base states (user tap, stem-base network, edge tracker) and the visible-stem bound.

Imported by :mod:`.measure` and :mod:`.scale`; imports :mod:`.fits`, :mod:`.up` and
:mod:`.stem_track`. The rope is 1.3 m up the stem from its base, so the base's pixel sets the
photo's scale by single-view metrology (:func:`base_metrology`). Where no base is found but the
stem was followed down to something that hides it, the metrology through that lowest point bounds
the distance from above (:func:`visible_stem_bound`; decision records
``docs/decisions/stem-base.md``, ``docs/decisions/visible-stem-bound.md``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..result import MeasureResult
from .config import ROPE_HEIGHT_M, StemBaseConfig, UpConfig
from .edges import TrunkEdges
from .fits import metrology_distance, normalize, pixel_rays, project_perpendicular
from .perception import Perception
from .stem_track import track_stem_base
from .up import StemAxis, stem_image_direction

__all__ = ["StemBase", "find_stem_base", "base_metrology", "visible_stem_bound"]


@dataclass
class StemBase:
    """The stem's base in the working image.

    Attributes
    ----------
    xy : (2,) the stem's front contact with the ground (pixels), or None.
    status : "user" (tapped), "network" / "network_weak" (the stem-base network, its probability
        at least / under :attr:`~.config.StemBaseConfig.p_strong`), "unconfirmed" (no segmented
        stem or edges to confirm a tracked base: not looked for), "tracked" (the edge tracker
        ended on what looks like the ground: a bound, not a base, unless
        :attr:`~.config.StemBaseConfig.tracked_base_sets_scale`), or the edge tracker's status
        ("ground" with that option, "occluded", "off_mask", "edge", "lost").
    track_info : the edge tracker's ``info`` when it ran (:func:`~.stem_track.track_stem_base`).
    """
    xy: np.ndarray | None
    status: str
    track_info: dict | None = None


def _base_from_network(perc: Perception, edges: TrunkEdges, axis: StemAxis, up_sources: dict,
                       res: MeasureResult, flags: list[str], config: StemBaseConfig,
                       up_config: UpConfig | None) -> StemBase | None:
    """The stem-base network's base (``perc.base_finder`` reads the strip below the rope), or None."""
    t_b = time.perf_counter()
    est = perc.base_finder(perc.rgb, axis.mid_xy,
                           stem_image_direction(perc.camera, axis.mid_xy, edges.along, up_sources, up_config),
                           edges.width_px)
    res.timings_ms["base"] = 1000 * (time.perf_counter() - t_b)
    res.debug["base_network"] = est
    if not est:
        return None
    flags.append("stem_base_from_network")
    return StemBase(np.asarray(est.xy, np.float64), "network_weak" if est.p_base < config.p_strong else "network")


def find_stem_base(perc: Perception, gray: np.ndarray, edges: TrunkEdges, axis: StemAxis, up_sources: dict,
                   res: MeasureResult, flags: list[str], config: StemBaseConfig | None = None,
                   up_config: UpConfig | None = None) -> StemBase:
    """The stem's base: where the user tapped (``perc.base_xy``), else the stem-base network's,
    else the edge tracker's (its outcome in ``res.debug["base_tracked"]``).

    Without a segmented stem to confirm where tracked edges end (the tree mask is the rope's band)
    or with edges that are not the stem's (``width_disagrees_rope`` in ``flags``), neither the
    network nor the tracker looks for the base (status "unconfirmed"). ``gray`` (H, W) float32.
    """
    cfg = config or StemBaseConfig()
    if perc.base_xy is not None:
        flags.append("stem_base_from_user")
        return StemBase(np.asarray(perc.base_xy, np.float64), "user")
    unconfirmed = bool(perc.extra.get("tree_mask_from_rope") or "width_disagrees_rope" in flags)
    if unconfirmed:
        return StemBase(None, "unconfirmed")
    if perc.base_finder is not None:
        base = _base_from_network(perc, edges, axis, up_sources, res, flags, cfg, up_config)
        if base is not None:
            return base
    xy, status, info = track_stem_base(gray, edges, perc.ground_mask, perc.tree_mask, rgb=perc.rgb,
                                       rope_half_px=perc.rope_half_px, config=cfg)
    res.debug["base_tracked"] = (xy, status, info)
    if status == "ground" and not cfg.tracked_base_sets_scale:
        # where the edges end the foot is, or something hides it: the end only bounds the distance
        return StemBase(None, "tracked", info)
    return StemBase(xy, status, info)


def base_metrology(camera, axis: StemAxis, xy) -> tuple[float, float]:
    """``(l_top, l_base)``: the distances (m) along the axis ray at the rope and along the ray to
    the stem's axis at its base, with ``xy`` (2,) the stem's front contact with the ground (the
    rope :data:`~.config.ROPE_HEIGHT_M` above it); non-positive where the geometry fails."""
    r_A, v = axis.r_A, axis.v
    r_B = pixel_rays(camera, np.asarray(xy, np.float64)[None])[0]
    lt, lb, _ = metrology_distance(r_A, r_B, v, ROPE_HEIGHT_M)
    if lt > 0 and lb > 0:
        # the visible base is the front contact point; the axis is ~rho further away
        B_axis = lb * r_B + lt * axis.sin_half * normalize(project_perpendicular(r_B, v))
        lt, lb, _ = metrology_distance(r_A, normalize(B_axis), v, ROPE_HEIGHT_M)
    return lt, lb


def visible_stem_bound(camera, axis: StemAxis, base: StemBase) -> tuple[float, str] | None:
    """``(l_top, status)``: the farthest the stem can be, from the metrology through the lowest
    point the edge tracker followed it to (the base is there or below), when no base was found
    and the tracker got that far; else None."""
    if base.xy is not None or base.track_info is None or base.track_info.get("end_xy") is None:
        return None
    lt, lb = base_metrology(camera, axis, base.track_info["end_xy"])
    if lt > 0 and lb > 0:
        return float(lt), base.status
    return None
