"""The roped stem's edge pair at the rope, checked against the rope band (:func:`stem_edges`).

Imported by :mod:`.measure`; imports numpy, cv2, :mod:`.edges` and the rope package's red-ness
map (``monodbh.toolkit.rope.redness_map``). The tree mask guides the edge search; the rope, tied
round the roped stem only, tells where a coarse mask took in a neighbouring trunk, or stopped
inside the stem, and its knot and loose ends are left out of the edges (decision record
``docs/decisions/stem-edges-rope-check.md``).
"""
from __future__ import annotations

import cv2
import numpy as np

from ..rope import redness_map
from .config import EdgeConfig, StemEdgesConfig
from .edges import (REASON_OUT_OF_PHOTO, TrunkEdges, band_mask, combine_edges, refit_edges, rope_curve,
                    rope_row_contrast, sample_image, trunk_edges)
from .perception import Perception

__all__ = ["stem_edges", "edges_two_pass", "edges_from_network", "edges_checked_by_rope", "edges_out_to_rope_end",
           "edges_off_rope_ends"]


def edges_two_pass(gray: np.ndarray, mask: np.ndarray, perc: Perception, config: StemEdgesConfig | None = None,
                   edge_config: EdgeConfig | None = None) -> TrunkEdges:
    """Trunk edges at the rope guided by ``mask`` (H, W) bool; a second pass samples across the
    stem as found (the rope band may be tilted or arced) and is kept unless its width differs
    from the first's by ``config.second_pass_max_change`` or more."""
    cfg = config or StemEdgesConfig()
    edges = trunk_edges(gray, mask, perc.rope_xy, perc.rope_dir, rope_half_px=perc.rope_half_px,
                        search_px=perc.edge_search_px, config=edge_config)
    if edges:
        across = np.array([edges.along[1], -edges.along[0]])
        mid0 = 0.5 * (edges.left_xy + edges.right_xy)
        e2 = trunk_edges(gray, mask, mid0, across, rope_half_px=perc.rope_half_px,
                         search_px=perc.edge_search_px, config=edge_config)
        if e2 and abs(e2.width_px / edges.width_px - 1) < cfg.second_pass_max_change:
            edges = e2
    return edges


def edges_from_network(perc: Perception, gray: np.ndarray, edges: TrunkEdges, config: StemEdgesConfig | None = None,
                       edge_config: EdgeConfig | None = None) -> tuple[TrunkEdges, int]:
    """The edges checked by the stem-edge network (``perc.edge_finder``): ``(edges, n_sides)``.

    The network reads a patch across the stem at the rope (centred between ``edges``, as wide)
    and says where each edge is. A side more than ``config.edge_net_tol_px`` pixels and
    ``config.edge_net_tol_frac`` of the width from the network's edge, where the network's
    probability mass there is at least ``config.edge_net_min_mass``, is searched again on the
    photo's gradient next to the network's edge (a band mask between the network's two edges
    guides :func:`~.edges.trunk_edges`, within 1.5 px or two of the network's columns); the
    other side stays. ``n_sides`` says how many sides moved (0: ``edges`` itself).
    """
    cfg = config or StemEdgesConfig()
    if perc.edge_finder is None or not edges:
        return edges, 0
    mid = 0.5 * (np.asarray(edges.left_xy, np.float64) + np.asarray(edges.right_xy, np.float64))
    est = perc.edge_finder(perc.rgb, mid, edges.along, float(edges.width_px))
    u = np.asarray(est.across, np.float64)
    s_grad = np.array([(edges.left_xy - mid) @ u, (edges.right_xy - mid) @ u])
    tol = max(cfg.edge_net_tol_px, cfg.edge_net_tol_frac * float(edges.width_px))
    move = (np.abs(est.offsets_px - s_grad) > tol) & (np.asarray(est.mass) >= cfg.edge_net_min_mass)
    if not move.any() or not est.offsets_px[1] - est.offsets_px[0] > 2.0:
        return edges, 0
    half_len = 4.0 * float(edges.width_px) + 40.0
    lo, hi = float(est.offsets_px[0]), float(est.offsets_px[1])
    c_net = mid + 0.5 * (lo + hi) * u            # on the same cross-section line, between the network's edges
    guide = band_mask(gray.shape, c_net, u, lo - 0.5 * (lo + hi), hi - 0.5 * (lo + hi), half_len)
    e_net = trunk_edges(gray, guide, c_net, u, rope_half_px=perc.rope_half_px,
                        search_px=max(1.5, 2.0 * est.px_per_col), config=edge_config)
    if not e_net:
        return edges, 0
    left = e_net if move[0] else edges
    right = e_net if move[1] else edges
    out = combine_edges(left, right, frame=edges)
    if not out.width_px > 0:
        return edges, 0
    return out, int(move.sum())


def _rope_contrast_fn(perc: Perception, gray_shape: tuple[int, int], edges: TrunkEdges, reach_px: float,
                      w3: float, config: StemEdgesConfig):
    """``contrast(lo, hi)``: the median red-ness contrast of the rope's row (against the rows
    beside it) at positions ``lo..hi`` across the stem (pixels from the rope centre, every
    0.5 px; nan for fewer than 3), read in a window of the photo around the stem only. The row
    follows the rope's centre line (``perc.rope_polyline``, a quadratic extended past its ends)
    within ``config.rope_curve_tolerance``; without one, a straight row that may sag by
    ``config.rope_straight_sag``."""
    c = np.asarray(perc.rope_xy, np.float64)
    h = max(0.5, float(perc.rope_half_px))
    curve = rope_curve(perc.rope_polyline, c, edges.across, edges.along)
    if curve is None:
        sag = config.rope_straight_sag * w3
        bend = sag
    else:
        sag = config.rope_curve_tolerance * w3 + 1.0
        s_max = reach_px + 1.0
        bend = sag + abs(curve[0]) + abs(curve[1]) * s_max + abs(curve[2]) * s_max ** 2
    m = int(np.ceil(reach_px + 6 * h + 8 + bend))
    H, W = gray_shape
    x0, y0 = max(0, int(c[0]) - m), max(0, int(c[1]) - m)
    x1, y1 = min(W, int(c[0]) + m + 1), min(H, int(c[1]) + m + 1)
    F = redness_map(np.ascontiguousarray(perc.rgb[y0:y1, x0:x1]))
    c_loc = c - (x0, y0)

    def profile(ss):
        return rope_row_contrast(F, c_loc, perc.rope_dir, edges.across, edges.along, ss,
                                 rope_half_px=h, sag_px=sag, curve=curve)

    def contrast(lo, hi):
        ss = np.arange(lo, hi, 0.5)
        if len(ss) < 3:
            return np.nan
        return float(np.median(profile(ss)))
    contrast.profile = profile      # (N,) positions -> (N,) contrasts
    return contrast


def _rope_across_stem(perc: Perception, gray_shape: tuple[int, int], edges: TrunkEdges, reach_ratio: float,
                      config: StemEdgesConfig):
    """The edges' positions along the rope's row and the rope's contrast across the stem.

    Returns
    -------
    ``(sL, sR, contrast, c_in)``: the left and right edges (pixels from the rope centre across
    the stem), :func:`_rope_contrast_fn` read up to ``reach_ratio`` of the stem's width past the
    farther edge, and the contrast across the stem's middle 70 %; None where the stem is 8 px or
    narrower or that contrast is not above ``config.rope_gap_min_contrast``.
    """
    c = np.asarray(perc.rope_xy, np.float64)
    u = edges.across
    sL, sR = float((edges.left_xy - c) @ u), float((edges.right_xy - c) @ u)
    w = sR - sL
    if w <= 8:
        return None
    contrast = _rope_contrast_fn(perc, gray_shape, edges, max(abs(sL), abs(sR)) + reach_ratio * w, w, config)
    c_in = contrast(sL + 0.15 * w, sR - 0.15 * w)
    if not c_in > config.rope_gap_min_contrast:
        return None
    return sL, sR, contrast, c_in


def _rope_end(profile, start: float, stop: float, level: float, gap_px: float) -> float:
    """Scanning the rope's row from ``start`` toward ``stop`` (pixels across the stem, every
    0.5 px), the last position at least ``level`` red before a run below it longer than
    ``gap_px``. ``profile``: (N,) positions -> (N,) contrasts."""
    ss = np.arange(start, stop, 0.5 if stop > start else -0.5)
    if not len(ss):
        return start
    ok = profile(ss) >= level
    last, miss = 0, 0.0
    for i, v in enumerate(ok):
        if v:
            last, miss = i, 0.0
        else:
            miss += 0.5
            if miss > gap_px:
                break
    return float(ss[last])


def _edge_strength(gray: np.ndarray, pts) -> float:
    """Median gradient magnitude (photo smoothed by a 1 px Gaussian) at a side's (N, 2) edge
    points; 0 without points."""
    if pts is None or len(pts) == 0:
        return 0.0
    P = np.asarray(pts, np.float64)
    H, W = gray.shape
    x0, y0 = max(0, int(P[:, 0].min()) - 6), max(0, int(P[:, 1].min()) - 6)
    x1, y1 = min(W, int(P[:, 0].max()) + 7), min(H, int(P[:, 1].max()) + 7)
    if x1 - x0 < 2 or y1 - y0 < 2:
        return 0.0
    g = cv2.GaussianBlur(np.ascontiguousarray(gray[y0:y1, x0:x1], np.float32), (0, 0), 1.0)
    gy, gx = np.gradient(g)
    m = np.hypot(gx, gy)
    xi = np.clip(np.round(P[:, 0]).astype(int) - x0, 0, m.shape[1] - 1)
    yi = np.clip(np.round(P[:, 1]).astype(int) - y0, 0, m.shape[0] - 1)
    return float(np.median(m[yi, xi]))


def edges_out_to_rope_end(gray: np.ndarray, perc: Perception, edges: TrunkEdges,
                          config: StemEdgesConfig | None = None,
                          edge_config: EdgeConfig | None = None) -> tuple[TrunkEdges, int]:
    """Move a side of the edge pair out to where the rope ends, when the rope runs on well past it.

    The rope is tied round the roped stem. Read along its centre line, where its row stays at
    least ``config.rope_extend_level`` as red as across the stem for more than
    ``config.rope_extend_min`` of the stem's width past a side's edge, both the mask and the rope
    band stopped inside the stem (a close stem seen from above, its flank in shade). That side's
    edge is searched at the rope's end, and kept only where it is at least
    ``config.rope_extend_min_strength`` times as strong (median gradient) as the edge it replaces:
    a rope's loose end or knot hanging on past the stem also reads as rope, but the silhouette it
    would move to is weaker than the stem's own.

    Parameters
    ----------
    gray : (H, W) float32 intensity of ``perc.rgb``.
    perc : :class:`~.perception.Perception` (its rope, rope centre line and photo are used).
    edges : the checked :class:`~.edges.TrunkEdges`.

    Returns
    -------
    (edges, n_sides): the edges and how many sides moved out (0-2).
    """
    cfg = config or StemEdgesConfig()
    if perc.rope_polyline is None or not edges:
        return edges, 0
    across = _rope_across_stem(perc, gray.shape, edges, cfg.rope_extend_max, cfg)
    if across is None:
        return edges, 0
    sL, sR, contrast, c_in = across
    c, u = np.asarray(perc.rope_xy, np.float64), edges.across
    w = sR - sL
    reach = cfg.rope_extend_max * w
    level, gap = cfg.rope_extend_level * c_in, max(2.0, cfg.rope_extend_gap * w)
    endL = _rope_end(contrast.profile, sL + 0.15 * w, sL - reach, level, gap)
    endR = _rope_end(contrast.profile, sR - 0.15 * w, sR + reach, level, gap)
    move = {"left": sL - endL > cfg.rope_extend_min * w, "right": endR - sR > cfg.rope_extend_min * w}
    if not any(move.values()):
        return edges, 0
    lo, hi = (endL if move["left"] else sL), (endR if move["right"] else sR)
    e = edges_two_pass(gray, band_mask(gray.shape, c, u, lo, hi, hi - lo), perc, cfg, edge_config)
    if not e:
        return edges, 0
    for side in ("left", "right"):
        if move[side] and (_edge_strength(gray, e.points.get(side))
                           < cfg.rope_extend_min_strength * _edge_strength(gray, edges.points.get(side))):
            move[side] = False
    if not any(move.values()):
        return edges, 0
    out = e if all(move.values()) else combine_edges(e if move["left"] else edges, e if move["right"] else edges,
                                                      frame=edges)
    if out.width_px <= edges.width_px:
        return edges, 0
    return out, int(move["left"]) + int(move["right"])


def edges_checked_by_rope(gray: np.ndarray, perc: Perception, edges: TrunkEdges,
                          config: StemEdgesConfig | None = None,
                          edge_config: EdgeConfig | None = None) -> tuple[TrunkEdges, int]:
    """Check each side of the mask-guided ``edges`` against the rope (``config.rope_gap_*``).

    The rope is tied round the roped stem only: where the mask's edge lies well beyond the end of
    the rope band and the rope's row there is no redder than the rows beside it, the mask has
    taken in a neighbouring trunk (or background) and that side's edge is searched at the rope's
    end instead. Where the rope goes on (faintly, e.g. in the stem's shade), the mask's edge stays.
    Where the rope band runs on past the mask's edge by more than its half thickness plus
    ``config.rope_overrun_extra_px``, and is red there, the mask's edge lies inside the stem (bark
    texture, a shadow) and that side's edge is searched at the rope's end too.

    Parameters
    ----------
    gray : (H, W) float32 intensity of ``perc.rgb``.
    perc : :class:`~.perception.Perception` (its rope, rope band mask and photo are used).
    edges : the mask-guided :class:`~.edges.TrunkEdges`.

    Returns
    -------
    (edges, n_sides): the checked edges and how many sides were replaced (0-2).
    """
    cfg = config or StemEdgesConfig()
    e3 = edges_two_pass(gray, perc.rope_band_mask, perc, cfg, edge_config)
    if not e3:
        return edges, 0
    c = np.asarray(perc.rope_xy, np.float64)
    u = edges.across
    sL1, sR1 = float((edges.left_xy - c) @ u), float((edges.right_xy - c) @ u)
    sL3, sR3 = float((e3.left_xy - c) @ u), float((e3.right_xy - c) @ u)
    w3 = sR3 - sL3
    gap_min = max(cfg.rope_gap_min_px, cfg.rope_gap_min_fraction * w3)
    gaps = {"left": sL3 - sL1, "right": sR1 - sR3}
    if w3 <= 4 or max(abs(g) for g in gaps.values()) <= gap_min:
        return edges, 0
    contrast = _rope_contrast_fn(perc, gray.shape, edges, max(abs(sL1), abs(sR1), abs(sL3), abs(sR3)), w3, cfg)
    c_in = contrast(sL3 + 0.15 * w3, sR3 - 0.15 * w3)
    if not c_in > cfg.rope_gap_min_contrast:
        return edges, 0
    left, right, n = edges, edges, 0
    # the mask runs on past the rope's end with no rope there: a merged neighbour
    if gaps["left"] > gap_min and contrast(sL1 + 1, sL3 - 1) < cfg.rope_gap_max_ratio * c_in:
        left, n = e3, n + 1
    if gaps["right"] > gap_min and contrast(sR3 + 1, sR1 - 1) < cfg.rope_gap_max_ratio * c_in:
        right, n = e3, n + 1
    # the rope runs on past the mask's edge by more than its band's end can overshoot the
    # silhouette (a round end cap, the blur): the mask edge lies inside the stem
    over_min = max(gap_min, float(perc.rope_half_px) + cfg.rope_overrun_extra_px)
    if -gaps["left"] > over_min and contrast(sL3 + 1, sL1 - 1) >= cfg.rope_overrun_min_ratio * c_in:
        left, n = e3, n + 1
    if -gaps["right"] > over_min and contrast(sR1 + 1, sR3 - 1) >= cfg.rope_overrun_min_ratio * c_in:
        right, n = e3, n + 1
    if n == 0:
        return edges, 0
    return (e3 if n == 2 else combine_edges(left, right, frame=edges)), n


def edges_off_rope_ends(perc: Perception, gray_shape: tuple[int, int], edges: TrunkEdges,
                        config: StemEdgesConfig | None = None) -> tuple[TrunkEdges, int]:
    """Leave out of each side's line the edge points that lie on the rope's knot or hanging ends.

    A knot tied on the stem's flank sticks out past the silhouette, and its loose ends hang down
    beside the stem: the edge search above and below the rope then finds their outer border
    instead of the bark's on some lines. Such a point has rope-red pixels just inside it (within
    ``config.rope_end_reach`` rope half-thicknesses), redder than the bark on its own line by at
    least ``config.rope_end_red_ratio`` of the rope's contrast across the stem; the bark's own
    border has bark there.

    Parameters
    ----------
    perc : :class:`~.perception.Perception` (its photo, rope and rope centre line are used).
    gray_shape : (H, W) of the working image.
    edges : :class:`~.edges.TrunkEdges` with their points.

    Returns
    -------
    (edges, n_points): the edges refitted without those points (each side keeps at least 3),
    and how many points were left out.
    """
    cfg = config or StemEdgesConfig()
    if not edges or cfg.rope_end_red_ratio <= 0 or not edges.points:
        return edges, 0
    pts = {k: np.asarray(edges.points.get(k), np.float64).reshape(-1, 2) for k in ("left", "right")}
    if min(len(p) for p in pts.values()) < 4:
        return edges, 0
    across = _rope_across_stem(perc, gray_shape, edges, 0.0, cfg)
    if across is None:
        return edges, 0
    c_in = across[3]
    u = edges.across
    h = max(0.5, float(perc.rope_half_px))
    allp = np.vstack(list(pts.values()))
    H, W = gray_shape
    m = int(np.ceil(cfg.rope_end_reach * h + 4))
    x0, y0 = max(0, int(allp[:, 0].min()) - m), max(0, int(allp[:, 1].min()) - m)
    x1, y1 = min(W, int(allp[:, 0].max()) + m + 1), min(H, int(allp[:, 1].max()) + m + 1)
    F = redness_map(np.ascontiguousarray(perc.rgb[y0:y1, x0:x1]))
    o = np.array([x0, y0], np.float64)
    inward = np.arange(0.5, cfg.rope_end_reach * h + 0.51, 0.5)
    a = np.array([-u[1], u[0]])
    slope = float(edges.along @ u) / float(edges.along @ a)      # the stem's direction: ds / dt
    keep, n_out = {}, 0
    for side, sign in (("left", 1.0), ("right", -1.0)):
        P = pts[side] - o
        other = pts["right" if side == "left" else "left"] - o
        # the bark on each point's line: the middle 60 % between it and the other side's line
        mid = np.median(other, 0)
        fr = np.linspace(0.2, 0.8, 13)
        Q = P[:, None, :] + fr[None, :, None] * ((mid - P) @ u)[:, None, None] * u[None, None, :]
        bark = np.median(sample_image(F, Q[..., 0], Q[..., 1]), 1)
        R = P[:, None, :] + sign * inward[None, :, None] * u[None, None, :]
        inner = sample_image(F, R[..., 0], R[..., 1]).max(1)
        k = inner - bark < cfg.rope_end_red_ratio * c_in
        if k.sum() < 3 or k.all():
            k = np.ones(len(P), bool)
        else:
            # left out only where they pull the side's line outward (the loose end beside the
            # stem), beyond the kept points' line (the stem's direction) by ``rope_end_min_out``
            t, s_ = P @ a, P @ u
            s0 = np.median(s_[k] - slope * t[k])
            out_px = -sign * (s_[~k] - s0 - slope * t[~k])
            if not np.median(out_px) > max(1.0, cfg.rope_end_min_out * h):
                k = np.ones(len(P), bool)
        keep[side] = k
        n_out += int((~k).sum())
    if n_out == 0:
        return edges, 0
    out = refit_edges(edges, keep)
    # a knot or a loose end only adds to the silhouette: a side whose refitted line lies further
    # out at the rope (its remaining points, far from the rope, tilt or shift it) keeps all its
    # points
    tol = max(1.0, h)
    wider = [side for side, g in _outward_px(edges, out).items() if not keep[side].all() and g > tol]
    if wider:
        for side in wider:
            n_out -= int((~keep[side]).sum())
            keep[side] = np.ones(len(keep[side]), bool)
        if n_out == 0:
            return edges, 0
        out = refit_edges(edges, keep)
        if max(_outward_px(edges, out).values()) > tol:
            return edges, 0
    return out, n_out


def _outward_px(edges: TrunkEdges, new: TrunkEdges) -> dict[str, float]:
    """How far (pixels, along ``edges.across``) each side of ``new`` lies outside ``edges``'s."""
    u = np.asarray(edges.across, np.float64)
    return {"left": float((np.asarray(edges.left_xy) - np.asarray(new.left_xy)) @ u),
            "right": float((np.asarray(new.right_xy) - np.asarray(edges.right_xy)) @ u)}


def stem_edges(perc: Perception, gray: np.ndarray, config: StemEdgesConfig | None = None,
               edge_config: EdgeConfig | None = None) -> tuple[TrunkEdges, list[str], float]:
    """The roped stem's silhouette edges at the rope, checked against the rope band.

    Parameters
    ----------
    perc : :class:`~.perception.Perception` (its edge mask, rope and rope band are used).
    gray : (H, W) float32 intensity of ``perc.rgb``.
    config, edge_config : :class:`~.config.StemEdgesConfig`, :class:`~.config.EdgeConfig`
        (defaults when None).

    Returns
    -------
    (edges, flags, width_vs_rope): :class:`~.edges.TrunkEdges` (falsy with a reason when not
    found), the flags this step raised, and ``|ln(edge width / rope length)|`` when the two
    disagree (a sigma term, else 0).
    """
    cfg = config or StemEdgesConfig()
    emask = perc.tree_mask if perc.edge_mask is None else perc.edge_mask
    edges = edges_two_pass(gray, emask, perc, cfg, edge_config)
    flags: list[str] = []
    if edges:
        # the network tells the stem's own edges from a neighbour's, a shadow's or the ground's
        edges, n_net = edges_from_network(perc, gray, edges, cfg, edge_config)
        if n_net:
            flags.append("edges_from_network")
    width_vs_rope = 0.0     # |ln(edge width / rope length)| when the two disagree (a sigma term)
    if edges and perc.rope_band_mask is not None:
        # a side where the coarse mask runs on beyond the rope's end with no rope there is a
        # neighbouring trunk merged in: that side's edge is taken at the rope's end
        edges, n_sides = edges_checked_by_rope(gray, perc, edges, cfg, edge_config)
        if n_sides:
            flags.append("edges_from_rope_band" if n_sides == 2 else "edge_at_rope_end")
        else:
            # the rope runs on well past an edge the mask and the band both stopped at
            edges, n_out = edges_out_to_rope_end(gray, perc, edges, cfg, edge_config)
            if n_out:
                flags.append("edges_out_to_rope_end")
    if edges and perc.rope_band_mask is not None:
        # a knot on the flank and its hanging ends are not the stem's border
        edges, n_knot = edges_off_rope_ends(perc, gray.shape, edges, cfg)
        if n_knot:
            flags.append("edge_points_on_rope_end")
    if edges and perc.rope_length_px and perc.rope_band_mask is not None:
        # the rope spans the stem: a stem much wider than the rope band means edges the rope
        # check could not settle, one much narrower edges inside the stem (bark, a shadow); the
        # gap widens the sigma
        ratio = edges.width_px / perc.rope_length_px
        if ratio > cfg.width_rope_ratio_max or ratio < cfg.width_rope_ratio_min:
            flags.append("width_disagrees_rope")
            width_vs_rope = float(abs(np.log(ratio)))
    if not edges and perc.rope_band_mask is not None:
        # the coarse mask's borders are nowhere near the stem's (e.g. a close stem merged with
        # its neighbour, the mask border tens of pixels off): the rope spans the stem, so its
        # band's ends guide the search instead
        e3 = edges_two_pass(gray, perc.rope_band_mask, perc, cfg, edge_config)
        lo, hi = cfg.band_width_ratio
        if e3 and (not perc.rope_length_px or lo < e3.width_px / perc.rope_length_px < hi):
            edges = e3
            flags.append("edges_from_rope_band")
        elif e3.reason == REASON_OUT_OF_PHOTO:
            edges = e3          # the more telling reason
    return edges, flags, width_vs_rope
