"""The metric scale: one candidate per source, and their combination into the axis distance at the rope.

Imported by :mod:`.measure`; imports :mod:`.fits`, :mod:`.stem_base`, :mod:`.depth_read` and
:mod:`.sigma`. Each candidate is ``(distance along the axis ray at the rope (m), relative 1-sigma)``;
the sources: ``pose`` (the calibrated pose's camera height, or the stem base with a pose),
``stem_base_user`` / ``stem_base`` / ``stem_base_weak`` (rope-to-base metrology with the base the
user tapped, the stem-base network's or the edge tracker's), ``rope_diameter`` (the rope as a ruler),
``ground_plane`` (the rope's height above the depth map's ground plane), ``camera_height`` (the
handheld prior on the camera's height above that plane), ``network`` (the depth network's own
metric output) and ``depth_gt`` (ground-truth depth). The source with the least typical error leads
and those that agree with it are averaged in (decision records ``docs/decisions/scale-combination.md``,
``docs/decisions/rope-ruler.md``, ``docs/decisions/distance-calibration.md``,
``docs/decisions/visible-stem-bound.md``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..result import MeasureResult
from .config import ROPE_HEIGHT_M, GeometryConfig, RopeRulerConfig, ScaleConfig
from .depth_read import stem_front_depth
from .edges import TrunkEdges
from .fits import PlaneFit, pixel_rays
from .perception import Perception
from .sigma import SigmaTables
from .stem_base import StemBase, base_metrology
from .up import StemAxis

__all__ = ["NETWORK_SCALE_SOURCES", "SOURCE_ORDER", "ScaleChoice", "scale_candidates", "candidate_stem_base",
           "candidate_rope_diameter", "rope_ruler_sigma", "candidate_pose", "axis_distance_from_depth",
           "candidate_ground_plane", "candidate_camera_height", "candidate_depth", "combine_candidates", "calibrate_distance",
           "beyond_visible_stem", "capped_by_visible_stem", "choose_scale"]

#: the scale sources that come from the depth network (their distances get the error model's
#: calibration, ``Perception.distance_calibration``)
NETWORK_SCALE_SOURCES = ("network", "ground_plane", "camera_height")
#: the order in which the sources that agreed with the leading one are named in ``scale_source``
SOURCE_ORDER = ("depth_gt", "pose", "stem_base_user", "ground_plane", "stem_base", "stem_base_weak",
                "rope_diameter", "camera_height", "network")
#: scale-candidate name -> its key in the network error model (sigma tables, manifest)
_SN_KEY = {"ground_plane": "ground_plane_network"}

Candidate = tuple[str, tuple[float, float]]


def candidate_stem_base(camera, axis: StemAxis, base: StemBase, up_sources: dict, tables: SigmaTables,
                        flags: list[str]) -> Candidate | None:
    """The rope-to-base metrology's candidate: named ``pose`` with a calibrated pose, else
    ``stem_base_user`` (tapped), ``stem_base_weak`` (a weak or an ambiguous network base: for the
    latter the geometric mean of its two bases' distances, the sigma widened by half their log
    ratio) or ``stem_base``. Flags
    ``stem_base_user_rejected`` for a tap that is not below the rope, ``stem_base_<status>``
    without a base."""
    if base.xy is None:
        flags.append(f"stem_base_{base.status}")
        return None
    lt, lb = base_metrology(camera, axis, base.xy)
    cand = None
    if lt > 0 and lb > 0:
        src = "pose" if "pose" in up_sources else "stem_base"
        if base.status == "user" and src == "stem_base":
            src = "stem_base_user"
        elif base.status in ("network_weak", "network_ambiguous") and src == "stem_base":
            src = "stem_base_weak"
        sigma = tables.by_perception.get(src, tables.network[src])
        if base.status == "network_ambiguous":
            # two feet, the network's and a lower one: between them, the sigma spanning both
            lt2, lb2 = base_metrology(camera, axis, base.track_info["lower_xy"])
            if lt2 > 0 and lb2 > 0:
                half = 0.5 * abs(float(np.log(lt / lt2)))
                lt, sigma = float(np.sqrt(lt * lt2)), float(np.hypot(sigma, half))
        cand = (src, (lt, sigma))
    if base.status == "user" and not (lt > 0 and lb > 0):
        flags.append("stem_base_user_rejected")      # the tapped point is not below the rope
    return cand


def candidate_rope_diameter(perc: Perception, axis: StemAxis, flags: list[str],
                            config: RopeRulerConfig | None = None) -> Candidate | None:
    """The rope as a ruler (``perc.rope_diameter_m`` given): a tube of known diameter D subtends
    D / rho radians at distance rho, seen across its band at the stem's front. Flags
    ``rope_too_thin_for_scale`` / ``rope_too_faint_for_scale`` where its thickness is not trusted,
    ``marker_not_read_for_scale`` where the rope was found but not seen as a line (by the rope
    finder or through the stem's profile: no thickness to read)."""
    cfg = config or RopeRulerConfig()
    if not perc.rope_diameter_m:
        return None
    if perc.rope_thickness_px is None:
        flags.append("marker_not_read_for_scale")    # found, but not seen as a line (no thickness)
        return None
    T_read = float(perc.rope_thickness_px)
    # the marker's thickness: edge to edge as read, or the half-maximum width (which reads narrow)
    T = T_read if perc.rope_thickness_edges else T_read / cfg.fwhm_ratio
    # blur widens thin ropes: the gate is on the pixels it was measured in (the full-resolution
    # photo's where it was read there)
    T_native = float(perc.rope_thickness_native_px or T_read)
    if T_native < cfg.min_px:
        flags.append("rope_too_thin_for_scale")
        return None
    if not (perc.rope_contrast or 0.0) >= cfg.min_contrast:
        flags.append("rope_too_faint_for_scale")
        return None
    n_band = np.array([-perc.rope_dir[1], perc.rope_dir[0]], np.float64)
    n_band /= np.linalg.norm(n_band) + 1e-12
    p0 = np.asarray(perc.rope_xy, np.float64)
    r1, r2 = pixel_rays(perc.camera, np.stack([p0 - 0.5 * T * n_band, p0 + 0.5 * T * n_band]))
    ang = float(np.arccos(np.clip(r1 @ r2, -1, 1)))
    if not ang > 0:
        return None
    rho = float(perc.rope_diameter_m) / ang       # camera -> the rope at the stem's front
    lt = (rho + 0.5 * float(perc.rope_diameter_m)) / max(1 - axis.sin_half, 1e-6)
    return "rope_diameter", (lt, rope_ruler_sigma(T_native, perc.rope_thickness_edges, cfg))


def rope_ruler_sigma(thickness_px: float, edges: bool, config: RopeRulerConfig | None = None) -> float:
    """The marker ruler's relative 1-sigma for a thickness of ``thickness_px`` pixels (those it
    was read in), read edge to edge (``edges``) or as the half-maximum width:
    ``hypot(floor, px / thickness_px)`` with :attr:`~.config.RopeRulerConfig.edge_sigma` or
    :attr:`~.config.RopeRulerConfig.fwhm_sigma` (decision record ``docs/decisions/rope-ruler.md``).

    Examples
    --------
    >>> round(rope_ruler_sigma(18.0, True), 3)
    0.035
    """
    cfg = config or RopeRulerConfig()
    floor, px = cfg.edge_sigma if edges else cfg.fwhm_sigma
    return float(np.hypot(floor, px / max(float(thickness_px), 1e-6)))


def candidate_pose(camera, axis: StemAxis, tables: SigmaTables) -> Candidate | None:
    """The calibrated pose's ground plane (the camera ``camera.pose.height_m`` above z = 0): the
    axis at the rope is :data:`~.config.ROPE_HEIGHT_M` above it."""
    h = float(camera.pose.height_m)
    nv = float(axis.up @ axis.v)
    den = float(axis.up @ axis.r_A)
    if not abs(den) > 1e-3:
        return None
    lt = (ROPE_HEIGHT_M * nv - h) / den
    cond = abs(ROPE_HEIGHT_M - h) / max(lt, 1e-6)
    if not lt > 0:
        return None
    return "pose", (lt, tables.model["pose"] + 0.01 / max(cond, 1e-3))


def axis_distance_from_depth(perc: Perception, edges: TrunkEdges, axis: StemAxis) -> float | None:
    """The distance along the axis ray at the rope the depth map gives (its front surface plus
    the radius, in the map's units), or None where it has no depth there."""
    z_front = stem_front_depth(perc, edges)
    if not np.isfinite(z_front):
        return None
    lam_front = z_front / max(axis.r_A[2], 1e-6)
    return lam_front / max(1 - axis.sin_half, 1e-6)      # axis = front surface + radius


def candidate_ground_plane(perc: Perception, axis: StemAxis, plane: PlaneFit, lam_axis: float,
                           tables: SigmaTables) -> Candidate | None:
    """The rope's height above the depth map's ground plane rescales the map's distance to
    :data:`~.config.ROPE_HEIGHT_M`; the plane's fit noise against that height widens the sigma."""
    PA = lam_axis * axis.r_A
    hA = float(plane.height(PA[None])[0])
    nv = float(plane.n @ axis.v)
    gp_key = "ground_plane" if perc.depth_is_metric else "ground_plane_network"
    if not (hA > 1e-6 and nv > 0.5):
        return None
    s = ROPE_HEIGHT_M * nv / hA
    sig = tables.by_perception[gp_key] + plane.rms_m / max(hA, 1e-6)
    return "ground_plane", (s * lam_axis, sig)


def candidate_camera_height(plane: PlaneFit, lam_axis: float, tables: SigmaTables,
                            config: ScaleConfig | None = None) -> Candidate | None:
    """The handheld prior: the phone held :attr:`~.config.ScaleConfig.camera_height_prior_m`
    above the depth map's ground plane rescales the map's distance."""
    cfg = config or ScaleConfig()
    h_cam = float(plane.c)
    if not h_cam > 1e-6:
        return None
    sig = np.hypot(tables.network["camera_height"], plane.rms_m / h_cam)
    return "camera_height", (cfg.camera_height_prior_m / h_cam * lam_axis, float(sig))


def candidate_depth(perc: Perception, lam_axis: float, tables: SigmaTables,
                    config: ScaleConfig | None = None) -> Candidate:
    """The depth map's own distance: ``depth_gt`` (ground truth) or ``network``."""
    if perc.depth_is_metric:
        return "depth_gt", (lam_axis, (config or ScaleConfig()).depth_gt_sigma)
    return "network", (lam_axis, tables.network["network"])


def scale_candidates(perc: Perception, edges: TrunkEdges, axis: StemAxis, base: StemBase, plane: PlaneFit | None,
                     up_sources: dict, tables: SigmaTables, flags: list[str],
                     config: GeometryConfig | None = None) -> dict[str, tuple[float, float]]:
    """All scale candidates ``{source: (axis distance (m), relative sigma)}``, in the order the
    combination visits them: stem base, rope diameter, pose, ground plane, camera height, depth."""
    cfg = config or GeometryConfig()
    cam = perc.camera
    found = [candidate_stem_base(cam, axis, base, up_sources, tables, flags),
             candidate_rope_diameter(perc, axis, flags, cfg.rope_ruler)]
    if "pose" in up_sources and not any(c is not None and c[0] == "pose" for c in found):
        found.append(candidate_pose(cam, axis, tables))
    lam_axis = None if perc.depth is None else axis_distance_from_depth(perc, edges, axis)
    if lam_axis is not None:
        if plane is not None:
            found.append(candidate_ground_plane(perc, axis, plane, lam_axis, tables))
            # (the camera's height along the vanishing-point up was measured worse than from the
            # plane's offset)
            if "pose" not in up_sources and not perc.depth_is_metric:
                found.append(candidate_camera_height(plane, lam_axis, tables, cfg.scale))
        found.append(candidate_depth(perc, lam_axis, tables, cfg.scale))
    return dict(c for c in found if c is not None)


@dataclass
class ScaleChoice:
    """The combined scale.

    Attributes
    ----------
    leader : the leading source; used : (list) it and the sources that agreed with it.
    lam : the axis distance at the rope (m); sig_rel : its relative 1-sigma.
    source : the ``scale_source`` string (leader first, then the others in :data:`SOURCE_ORDER`).
    """
    leader: str
    used: list[str]
    lam: float
    sig_rel: float
    source: str


def combine_candidates(cands: dict[str, tuple[float, float]], *, rank: dict, correlated: bool, flags: list[str],
                       config: ScaleConfig | None = None) -> ScaleChoice:
    """Inverse-variance combination of the candidates that agree with the leading one.

    The leading source has the least typical error in ``rank`` (by error-model key; the
    shipped networks' measured ``rank_network``), else the least sigma, or its own sigma where
    that is less (a wide marker read edge to edge); sources whose typical
    errors are within :attr:`~.config.ScaleConfig.rank_tie` of the least are tied, and of those
    the candidate with the least sigma leads. Each other candidate
    (never ``network`` unless it leads) within :attr:`~.config.ScaleConfig.agree_sigmas` combined
    sigmas is averaged in; the others are flagged ``scale_disagree_<source>``. With
    ``correlated`` sources (network perception: one depth map and one set of masks) agreeing does
    not shrink the sigma below the best single source's.
    """
    cfg = config or ScaleConfig()
    # a reading whose own sigma is less than its source's typical error (a wide marker read edge
    # to edge across many pixels: its sigma follows its thickness) is that precise
    typical = {k: min(rank.get(_SN_KEY.get(k, k), cands[k][1]), cands[k][1]) for k in cands}
    least = min(typical.values())
    # typical errors this close are a tie (their own sampling error): the lighter tail leads
    tied = [k for k in cands if typical[k] <= least * (1 + cfg.rank_tie)]
    best = min(tied, key=lambda k: (cands[k][1], typical[k]))
    lam, sig_rel = cands[best]
    used = [best]
    for k, (l2, s2) in cands.items():
        if k == best or k == "network":
            continue
        if abs(l2 / lam - 1) < cfg.agree_sigmas * np.hypot(s2, sig_rel):
            w1, w2 = 1 / sig_rel ** 2, 1 / s2 ** 2
            lam = (w1 * lam + w2 * l2) / (w1 + w2)
            sig_rel = 1 / np.sqrt(w1 + w2)
            used.append(k)
        else:
            flags.append(f"scale_disagree_{k}")
    if correlated and len(used) > 1:
        sig_rel = min(cands[k][1] for k in used)
    source = "+".join([best] + sorted((k for k in used if k != best), key=SOURCE_ORDER.index))
    return ScaleChoice(leader=best, used=used, lam=lam, sig_rel=sig_rel, source=source)


def calibrate_distance(lam: float, sig_rel: float, calib: dict) -> tuple[float, float]:
    """The error model's calibration of a network-led distance: ``ln d -> a + b ln d`` shrinks the
    network's distances (noisier than the spread of distances people stand at) towards the
    typical distance; its measured ``sigma`` (when given) replaces ``sig_rel``
    (decision record ``docs/decisions/distance-calibration.md``)."""
    lam = float(np.exp(calib["a"] + calib["b"] * np.log(lam)))
    if calib.get("sigma"):
        sig_rel = float(calib["sigma"])
    return lam, sig_rel


def beyond_visible_stem(lam: float, leader: str, bound: tuple[float, str] | None,
                        config: ScaleConfig | None = None) -> bool:
    """Whether ``lam`` lies beyond the visible stem's ``bound``
    (:func:`~.stem_base.visible_stem_bound`): a bound of :attr:`~.config.ScaleConfig.bound_statuses`,
    a leading source not in :attr:`~.config.ScaleConfig.precise_sources`, and ``lam`` beyond the
    bound by more than :attr:`~.config.ScaleConfig.bound_slack`."""
    cfg = config or ScaleConfig()
    return (bound is not None and bound[1] in cfg.bound_statuses and leader not in cfg.precise_sources
            and lam > bound[0] * (1 + cfg.bound_slack))


def capped_by_visible_stem(lam: float, leader: str, bound: tuple[float, str] | None,
                           config: ScaleConfig | None = None, sig_rel: float = float("inf")) -> bool:
    """Whether the visible stem's ``bound`` caps ``lam``: beyond it (:func:`beyond_visible_stem`)
    and the leading scale's relative 1-sigma ``sig_rel`` at least
    :attr:`~.config.ScaleConfig.bound_min_sigma` (a marker read to a few per cent is not capped).

    Examples
    --------
    >>> capped_by_visible_stem(5.2, "network", (5.0, "occluded"), sig_rel=0.3)
    True
    >>> capped_by_visible_stem(5.2, "rope_diameter", (5.0, "occluded"), sig_rel=0.04)
    False
    """
    cfg = config or ScaleConfig()
    return beyond_visible_stem(lam, leader, bound, cfg) and sig_rel >= cfg.bound_min_sigma


def choose_scale(perc: Perception, cands: dict[str, tuple[float, float]], bound: tuple[float, str] | None,
                 res: MeasureResult, flags: list[str], config: ScaleConfig | None = None) -> ScaleChoice:
    """The scale from the candidates: combined (:func:`combine_candidates`), calibrated where the
    depth network leads (:func:`calibrate_distance`, flag ``distance_calibrated``), capped by the
    visible stem (flag ``scale_capped_by_visible_stem``) with network perception. Sets
    ``res.scale_source`` and the ``res.debug`` entries ``scale_leader``, ``lam_combined``,
    ``lam_uncalibrated``, ``lam_before_bound``."""
    cfg = config or ScaleConfig()
    net = perc.source == "network"
    rank = (perc.rank_network or {}) if net else {}
    ch = combine_candidates(cands, rank=rank, correlated=net, flags=flags, config=cfg)
    res.scale_source = ch.source
    res.debug["scale_leader"], res.debug["lam_combined"] = ch.leader, float(ch.lam)
    calib = perc.distance_calibration if net else None
    if calib and ch.leader in NETWORK_SCALE_SOURCES:
        res.debug["lam_uncalibrated"] = float(ch.lam)
        ch.lam, ch.sig_rel = calibrate_distance(ch.lam, ch.sig_rel, calib)
        flags.append("distance_calibrated")
    res.debug["lam_before_bound"] = float(ch.lam)
    if net and capped_by_visible_stem(ch.lam, ch.leader, bound, cfg, ch.sig_rel):
        # the stem was followed down to where something hides it: its base is there or lower,
        # so the rope-to-base metrology through that point is the farthest the stem can be
        ch.lam = bound[0]
        flags.append("scale_capped_by_visible_stem")
        res.scale_source = "visible_stem+" + res.scale_source
    elif net and beyond_visible_stem(ch.lam, ch.leader, bound, cfg):
        # a precise marker reading against a followed stem that may have run on into its shadow
        flags.append("scale_disagree_visible_stem")
    if ch.leader == "network":
        flags.append("scale_from_network")
    return ch
