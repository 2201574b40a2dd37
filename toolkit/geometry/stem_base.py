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
        at least / under :attr:`~.config.StemBaseConfig.p_strong`), "network_ambiguous" (the
        network puts the base lower in a strip cut a little differently: ``track_info["lower_xy"]``),
        "unconfirmed" (the network saw
        no base, and there is no segmented stem or no edges to confirm a tracked one: the
        tracker does not run), "tracked" (the edge tracker
        ended on what looks like the ground: a bound, not a base, unless
        :attr:`~.config.StemBaseConfig.tracked_base_sets_scale`), or the edge tracker's status
        ("ground" with that option, "occluded", "off_mask", "edge", "lost"); "occluded" also
        where the network's base lies above the segmented stem's end (something in front of
        the stem: flag ``stem_base_above_visible_stem``).
    track_info : the edge tracker's ``info`` when it ran (:func:`~.stem_track.track_stem_base`);
        for a refused network base ``{"end_xy": the segmented stem's lowest point, "network_xy"}``.
    """
    xy: np.ndarray | None
    status: str
    track_info: dict | None = None


def _stem_mask_end(mask: np.ndarray, c: np.ndarray, a: np.ndarray, width_px: float, t_max: float) -> float:
    """How far (pixels from ``c`` down the unit direction ``a``) the (H, W) bool ``mask`` covers
    the stem's middle: rows whose central 60 % is at least half inside the mask, followed down
    across gaps of up to half a stem width (leaves in front); 0 where the first rows are not."""
    H, W = mask.shape
    u = np.array([a[1], -a[0]])
    t = np.arange(0.0, max(1.0, t_max), 1.0)
    s = np.linspace(-0.3, 0.3, 9) * width_px
    P = c[None, None] + t[:, None, None] * a[None, None] + s[None, :, None] * u[None, None]
    x, y = np.rint(P[..., 0]).astype(int), np.rint(P[..., 1]).astype(int)
    inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
    hit = np.zeros(x.shape, bool)
    hit[inside] = mask[y[inside], x[inside]]
    rows = t[hit.sum(1) >= 0.5 * len(s)]
    end, max_gap = 0.0, max(3.0, 0.5 * width_px)
    for r in rows:
        if r - end > max_gap:
            break
        end = float(r)
    return end


def _below_visible_stem(perc: Perception, edges: TrunkEdges, xy: np.ndarray,
                        config: StemBaseConfig) -> np.ndarray | None:
    """The lowest point of the segmented stem (2,) where it runs on below the base ``xy`` by more
    than ``config.mask_overrun_max`` of the rope-to-base span, else None."""
    if perc.tree_mask is None:
        return None
    c = 0.5 * (np.asarray(edges.left_xy, np.float64) + np.asarray(edges.right_xy, np.float64))
    a = normalize(np.asarray(edges.along, np.float64))
    t_base = float((xy - c) @ a)
    if t_base < 0:
        a, t_base = -a, -t_base
    if t_base <= 0:
        return None
    t_end = _stem_mask_end(np.asarray(perc.tree_mask, bool), c, a, float(edges.width_px),
                           float(np.hypot(*perc.tree_mask.shape)))
    if t_end <= (1.0 + config.mask_overrun_max) * t_base:
        return None
    return c + t_end * a


def _lower_base_nearby(find, rgb: np.ndarray, top: np.ndarray, along: np.ndarray, width_px: float,
                       xy: np.ndarray, config: StemBaseConfig) -> tuple[float, np.ndarray | None]:
    """The lowest base the network finds when its strip is cut a little differently
    (``config.ambiguity_strips``: width factor, shift across in stem widths, rotation in
    degrees): ``(how much lower, as a fraction of the rope-to-base span; its pixel (2,))``,
    ``(0, None)`` where none is lower.

    A foot hidden in grass or behind a bush leaves the network to choose between the top of what
    hides it and a lower end; a strip cut as the stem's edges could also have been found may
    take the other. ``find`` is the network's ``(rgb, top, along, width) -> estimate``."""
    a = normalize(np.asarray(along, np.float64))
    u = np.array([a[1], -a[0]])
    t0 = float((np.asarray(xy, np.float64) - top) @ a)
    lower, lower_xy = 0.0, None
    if not t0 > 0:
        return lower, lower_xy
    for k_w, shift_w, rot_deg in config.ambiguity_strips:
        c, s_ = np.cos(np.radians(rot_deg)), np.sin(np.radians(rot_deg))
        a2 = np.array([c * a[0] - s_ * a[1], s_ * a[0] + c * a[1]])
        est = find(rgb, top + shift_w * width_px * u, a2, k_w * width_px)
        if est:
            d = (float((np.asarray(est.xy, np.float64) - top) @ a) - t0) / t0
            if d > lower:
                lower, lower_xy = d, np.asarray(est.xy, np.float64)
    return lower, lower_xy


def _base_from_network(perc: Perception, edges: TrunkEdges, axis: StemAxis, up_sources: dict,
                       res: MeasureResult, flags: list[str], config: StemBaseConfig,
                       up_config: UpConfig | None) -> StemBase | None:
    """The stem-base network's base (``perc.base_finder`` reads the strip below the rope), or None."""
    t_b = time.perf_counter()
    top = np.asarray(axis.mid_xy, np.float64)
    along = stem_image_direction(perc.camera, axis.mid_xy, edges.along, up_sources, up_config)
    est = perc.base_finder(perc.rgb, top, along, edges.width_px)
    res.timings_ms["base"] = 1000 * (time.perf_counter() - t_b)
    res.debug["base_network"] = est
    if not est:
        return None
    xy = np.asarray(est.xy, np.float64)
    # (a tree mask drawn from the rope band is no segmented stem to see past the base)
    end = None if perc.extra.get("tree_mask_from_rope") else _below_visible_stem(perc, edges, xy, config)
    if end is not None:
        # the stem is seen lower than that "base": something in front of the stem ends there
        flags.append("stem_base_above_visible_stem")
        return StemBase(None, "occluded", {"end_xy": end, "network_xy": xy})
    flags.append("stem_base_from_network")
    if getattr(est, "network", "stem_base") == "stem_base_net":
        flags.append("stem_base_second_network")
    t_b = time.perf_counter()
    lower, lower_xy = (_lower_base_nearby(perc.base_finder, perc.rgb, top, along, float(edges.width_px), xy, config)
                       if config.ambiguity_strips and est.p_base < config.ambiguity_p_max else (0.0, None))
    res.timings_ms["base"] += 1000 * (time.perf_counter() - t_b)
    res.debug["base_lower_nearby"] = lower
    if lower > config.ambiguity_max_lower:
        # a strip cut a little differently finds the foot lower: what was taken may be the top of
        # something hiding it; both stay (the scale reads between them, its sigma spans them)
        flags.append("stem_base_ambiguous")
        return StemBase(xy, "network_ambiguous", {"lower_xy": lower_xy})
    return StemBase(xy, "network_weak" if est.p_base < config.p_strong else "network")


def find_stem_base(perc: Perception, gray: np.ndarray, edges: TrunkEdges, axis: StemAxis, up_sources: dict,
                   res: MeasureResult, flags: list[str], config: StemBaseConfig | None = None,
                   up_config: UpConfig | None = None) -> StemBase:
    """The stem's base: where the user tapped (``perc.base_xy``), else the stem-base network's,
    else the edge tracker's (its outcome in ``res.debug["base_tracked"]``).

    The network reads the strip below the rope whatever the mask and edges. Without a segmented
    stem to confirm where tracked edges end (the tree mask is the rope's band) or with edges that
    may not be the stem's (``width_disagrees_rope`` in ``flags``), the tracker does not follow
    them (status "unconfirmed" where the network saw no base). ``gray`` (H, W) float32.
    """
    cfg = config or StemBaseConfig()
    if perc.base_xy is not None:
        flags.append("stem_base_from_user")
        return StemBase(np.asarray(perc.base_xy, np.float64), "user")
    if perc.base_finder is not None:
        base = _base_from_network(perc, edges, axis, up_sources, res, flags, cfg, up_config)
        if base is not None:
            return base
    if perc.extra.get("tree_mask_from_rope") or "width_disagrees_rope" in flags:
        # no segmented stem to tell where tracked edges end, or edges that may not be the stem's
        return StemBase(None, "unconfirmed")
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
