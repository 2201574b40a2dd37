"""Classical detection of the red measuring rope tied around a stem at breast height (the band
detector); imported by the pipeline and the rope benchmarks.

The rope is a thin, red, roughly horizontal band (an ellipse arc of a ring seen from slightly
above or below) that crosses a trunk from edge to edge. Detection, without a learned model
(:func:`detect_rope`, its stages the private functions below):

1. **Red-ness and thin-line contrast** (:mod:`.redness`) on a copy downscaled to
   ``work_long_side_px`` pixels and two pyramid levels below it (thick ropes).
2. **Pieces and bands** (:mod:`.band_segments`): connected components of the contrast map,
   linked end to end, runs of linked pieces fitted with a quadratic centre line.
3. **Score** (:mod:`.band_features`): a log-odds from the band and its surroundings. With a
   ``tree_mask``, bands that lie on the mask and span the trunk's width there are preferred.
4. **Decision**: the best band scoring above ``min_score``; a rival within ``ambiguity_margin``
   makes the result ambiguous unless one band is clearly longer (the nearer, larger roped
   trunk). ``pick_xy`` selects the nearest candidate instead.
5. The chosen band is refined at full resolution (:mod:`.band_refine`); a band that turns out
   blob-like there is dropped and the next one taken.

Ropes whose red-ness contrast to the bark is below ~0.02 (thin ropes far away in haze) are mostly
missed; flagging tape that is not orange looks like a rope here and is left to the caller's
``height_check``.

Examples
--------
>>> det = detect_rope(rgb)                          # doctest: +SKIP
>>> if det:                                         # doctest: +SKIP
...     print(det.center_xy, det.thickness_px)
... else:
...     print(det.reason)
"""
from __future__ import annotations

import time
from typing import Callable

import cv2
import numpy as np

from .band_features import BoxCounts, band_context, candidate_features, candidate_score, context_maps
from .band_refine import refine_band
from .band_segments import SEG_KEYS, BandFit, band_runs, diverse_runs, fit_band, line_pieces, link_pieces, piece_ends
from .config import BandConfig
from .detection import NO_ROPE, RopeCandidate, RopeDetection
from .geometry import distance_to_vertices, trunk_run
from .redness import line_contrast, redness_map

__all__ = ["detect_rope"]


def detect_rope(rgb: np.ndarray, tree_mask: np.ndarray | None = None, *,
                pick_xy: tuple[float, float] | None = None,
                height_check: Callable[[RopeCandidate], bool] | None = None,
                weak_score: float | None = None, min_score: float | None = None,
                ambiguity_margin: float | None = None, weights: dict | None = None,
                config: BandConfig | None = None) -> RopeDetection:
    """Find the red rope tied around a trunk.

    Parameters
    ----------
    rgb : (H, W, 3) uint8 RGB photo.
    tree_mask : (H, W) bool trunk/tree pixels, optional; bands that lie on the mask and span the
        trunk's width there are preferred, bands off the mask are penalised.
    pick_xy : (x, y) full-resolution pixel: choose the candidate nearest to it (resolves ambiguity).
    height_check : optional callable ``candidate -> bool`` from the caller (e.g. "is this about
        1.3 m above the ground?"); candidates for which it returns False are dropped.
    weak_score : when no candidate scores above ``min_score``, the best one above
        ``weak_score`` is returned with ``weak=True`` (rivals judged among those), for the
        caller to verify with other evidence (docs/decisions/rope-weak-score.md). ``None``: no
        weak results.
    min_score, ambiguity_margin, weights : this call's values instead of the configuration's
        ``min_score``, ``ambiguity_margin`` and ``score_weights``.
    config : the detector's parameters (default :class:`~.config.BandConfig`).

    Returns
    -------
    RopeDetection
        ``center_xy``/``polyline``/``mask`` in full-resolution pixels of ``rgb``.
    """
    cfg = BandConfig() if config is None else config
    min_score = cfg.min_score if min_score is None else min_score
    margin = cfg.ambiguity_margin if ambiguity_margin is None else ambiguity_margin
    weights = cfg.score_weights if weights is None else weights
    t0 = time.perf_counter()
    tm: dict[str, float] = {}

    def lap(name):
        tm[name] = round(1000 * (time.perf_counter() - t0) - sum(tm.values()), 2)

    rgb, tree_mask = _checked(rgb, tree_mask)
    small = _downscale(rgb, cfg.work_long_side_px)
    lap("resize")
    segs, counts, F0, Rs = _line_maps(small, cfg)
    lap("lines")
    if not segs:
        return RopeDetection(False, NO_ROPE, timings_ms=tm)
    fits = _band_fits(_piece_table(segs, cfg), cfg, max(small.shape[:2]))
    lap("bands")
    maps = context_maps(small, counts, F0, Rs)
    scale = (rgb.shape[1] / small.shape[1], rgb.shape[0] / small.shape[0])
    cands = [_candidate(f, maps, weights, cfg, scale, tree_mask) for f in fits]
    cands = _ranked(cands, height_check)
    lap("score")
    det = _decide(rgb, cands, tree_mask, pick_xy, min_score, weak_score, margin, cfg, tm)
    if det.found:
        lap("refine")
        tm["total"] = round(1000 * (time.perf_counter() - t0), 2)
    return det


def _checked(rgb, tree_mask):
    """The inputs as arrays, checked: ``(rgb (H, W, 3) uint8, tree_mask (H, W) bool or None)``."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    H, W = rgb.shape[:2]
    if tree_mask is not None:
        tree_mask = np.asarray(tree_mask, bool)
        if tree_mask.shape != (H, W):
            raise ValueError(f"tree_mask shape {tree_mask.shape} != image {(H, W)}")
    return rgb, tree_mask


def _downscale(rgb: np.ndarray, long_side: int) -> np.ndarray:
    """Shrink so that the long side is at most ``long_side``.

    Exact 2x area halvings (fast) while the image is at least twice too large, then one linear
    step by a factor below 2 (a line 1 px wide after it still spans >= 1 sample).
    """
    img = rgb
    while max(img.shape[:2]) >= 2 * long_side:
        img = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)
    H, W = img.shape[:2]
    if max(H, W) > long_side:
        s = long_side / max(H, W)
        img = cv2.resize(img, (round(W * s), round(H * s)), interpolation=cv2.INTER_LINEAR)
    return img


def _line_maps(small: np.ndarray, cfg: BandConfig):
    """Red-ness, thin-line contrast and pieces on the working copy and up to two pyramid levels.

    Returns
    -------
    (segs, counts, F0, Rs) : the piece table of each level that has pieces, :class:`BoxCounts`
    of the level-0 piece pixels, the level-0 red-ness and each level's contrast map.
    """
    thr = cfg.piece_threshold
    segs, img, Rs = [], small, []
    for level in range(cfg.pyramid_levels):
        F = redness_map(img)
        R = line_contrast(F, sigma_x=cfg.sigma_x_px)
        Rs.append(R)
        if level == 0:
            counts = BoxCounts(R > thr)
            F0 = F
        sg = line_pieces(R, F, img, thr=thr, min_len=5.0, level=level)
        if sg is not None:
            segs.append(sg)
        if level < cfg.pyramid_levels - 1 and min(img.shape[:2]) >= 64:
            img = cv2.pyrDown(img)
        else:
            break
    return segs, counts, F0, Rs


def _piece_table(segs: list[dict], cfg: BandConfig) -> dict:
    """All levels' pieces in one table, faint short ones dropped, at most ``max_segments`` (the
    most contrasted), with their ends (:func:`.band_segments.piece_ends`)."""
    seg = {k: np.concatenate([g[k] for g in segs]) for k in SEG_KEYS}
    keep = (seg["contrast"] >= cfg.min_contrast) | (seg["length"] >= 10)
    seg = {k: v[keep] for k, v in seg.items()}
    if len(seg["cx"]) > cfg.max_segments:
        top = np.argsort(-seg["contrast"] * np.sqrt(seg["length"]))[:cfg.max_segments]
        seg = {k: v[top] for k, v in seg.items()}
    return piece_ends(seg)


def _band_fits(seg: dict, cfg: BandConfig, long_side: int) -> list[BandFit]:
    """The bands to score: the best runs by band score plus diverse ones (``deep``)."""
    n = cfg.max_candidates
    runs = diverse_runs(seg, band_runs(seg, link_pieces(seg), cfg.min_contrast), n,
                        cell=max(32.0, long_side / 16.0), extra=n // 2)
    return [fit_band(seg, idx, deep=k >= n) for k, idx in enumerate(runs)]


def _candidate(fit: BandFit, maps, weights: dict, cfg: BandConfig, scale, tree_mask) -> RopeCandidate:
    """The scored candidate of a band, in full-resolution pixels (``scale`` = full / working)."""
    ctx = band_context(fit, maps, cfg)
    feats = candidate_features(fit, ctx)
    score = candidate_score(fit, feats, weights, cfg)
    sx, sy = scale
    poly = (fit.polyline + 0.5) * np.array([sx, sy], np.float32) - 0.5
    center = ((fit.center_xy[0] + 0.5) * sx - 0.5, (fit.center_xy[1] + 0.5) * sy - 0.5)
    span = float("nan")
    if tree_mask is not None:
        span, gain = _tree_mask_weight(poly, center[0], tree_mask)
        score = score + gain
    return RopeCandidate(
        center_xy=center, direction=fit.direction, length_px=fit.length_px * sx,
        thickness_px=fit.thickness_px * sy, score=score, contrast=fit.contrast, coverage=fit.coverage,
        span=span, hue=fit.hue, polyline=poly, features=feats, level=fit.level, resid=fit.resid,
        members=fit.members, clutter=ctx.clutter, density=ctx.density, edges=ctx.edges, step=ctx.step,
        red=fit.red, red_area=ctx.red_area, peaky=ctx.peaky, edge_snr=ctx.edge_snr, corr=ctx.corr, deep=fit.deep)


def _tree_mask_weight(poly: np.ndarray, xc: float, tree_mask: np.ndarray) -> tuple[float, float]:
    """``(span, log-odds gain)`` of a band by how much of it lies on the tree mask and how much
    of the trunk's width there it spans."""
    H, W = tree_mask.shape
    xi = np.clip(np.round(poly[:, 0]).astype(int), 0, W - 1)
    yi = np.clip(np.round(poly[:, 1]).astype(int), 0, H - 1)
    on = float(tree_mask[yi, xi].mean())
    l, r = trunk_run(tree_mask, poly, xc)
    if r >= l:
        span = float(np.clip((min(r, poly[-1, 0]) - max(l, poly[0, 0])) / max(r - l + 1, 1), 0.0, 1.0))
    else:
        span = 0.0
    return span, float(np.log((0.2 + 0.8 * on) * (0.3 + 0.7 * span)))


def _ranked(cands: list[RopeCandidate], height_check) -> list[RopeCandidate]:
    """Candidates passing ``height_check`` with a finite score, best first, duplicates dropped."""
    if height_check is not None:
        cands = [c for c in cands if height_check(c)]
    cands = [c for c in cands if np.isfinite(c.score)]
    cands.sort(key=lambda c: -c.score)
    return _dedupe(cands)


def _dedupe(cands: list[RopeCandidate]) -> list[RopeCandidate]:
    """Drop candidates overlapping a better one (same band at two levels, or a sub-chain)."""
    out = []
    for c in cands:
        dup = False
        for o in out:
            x0, x1 = o.polyline[0, 0], o.polyline[-1, 0]
            if x0 - 2 <= c.center_xy[0] <= x1 + 2:
                yo = np.interp(c.center_xy[0], o.polyline[:, 0], o.polyline[:, 1])
                if abs(yo - c.center_xy[1]) < 2 + o.thickness_px + c.thickness_px:
                    dup = True
                    break
        if not dup:
            out.append(c)
    return out


def _decide(rgb, cands, tree_mask, pick_xy, min_score, weak_score, margin, cfg: BandConfig,
            tm: dict) -> RopeDetection:
    """The detection: the chosen candidate refined at full resolution (a chosen band that turns
    out blob-like there is dropped and the next one chosen, up to 3 times), an ambiguity, or none
    (``tm``: the timings dict it carries, still filled by the caller)."""
    best = None
    for _ in range(3):
        best = _choose(cands, pick_xy, min_score, margin, cfg.nearer_ratio)
        if best is None and weak_score is not None and pick_xy is None:
            best = _choose(cands, None, weak_score, margin, cfg.nearer_ratio)
        if best is None or isinstance(best, str):
            break
        ref = refine_band(rgb, best, tree_mask)
        arc = float(np.hypot(*np.diff(ref.polyline, axis=0).T).sum()) + 1.0
        if arc >= cfg.min_elongation * max(ref.thickness_px, 0.7):
            return RopeDetection(True, "", center_xy=ref.center_xy, direction=ref.direction, polyline=ref.polyline,
                                 thickness_px=ref.thickness_px, mask=ref.mask, score=best.score, candidates=cands,
                                 weak=pick_xy is None and not best.score > min_score, timings_ms=tm)
        cands = [c for c in cands if c is not best]
    if isinstance(best, str):
        return RopeDetection(False, best, candidates=cands, ambiguous=True, timings_ms=tm)
    return RopeDetection(False, NO_ROPE, candidates=cands, timings_ms=tm)


def _choose(cands: list[RopeCandidate], pick_xy, min_score: float, ambiguity_margin: float,
            nearer_ratio: float) -> RopeCandidate | str | None:
    """The candidate to report, an ambiguity message, or None (see :func:`detect_rope`)."""
    if pick_xy is not None:
        if not cands:
            return None
        near = [c for c in cands[:30] if c.score > min_score - 3.0] or cands[:30]
        return min(near, key=lambda c: distance_to_vertices(c.polyline, pick_xy))
    ropes = [c for c in cands if c.score > min_score]
    if not ropes:
        return None
    best = ropes[0]
    rivals = [c for c in ropes[1:] if c.score >= best.score - ambiguity_margin]
    if not rivals:
        return best
    if all(_overlapping(best, c) for c in rivals):
        # the same rope found more than once (pyramid levels, pieces): the longest band
        return max([best] + rivals, key=lambda c: c.length_px)
    group = [best] + rivals
    longest = max(group, key=lambda c: c.length_px)
    if all(longest.length_px >= nearer_ratio * c.length_px for c in group if c is not longest):
        return longest
    c1, c2 = group[0], group[1]
    return (f"two rope candidates at ({c1.center_xy[0]:.0f},{c1.center_xy[1]:.0f}) and "
            f"({c2.center_xy[0]:.0f},{c2.center_xy[1]:.0f}) (e.g. two roped trees); choose one with --pick X,Y")


def _overlapping(a: RopeCandidate, b: RopeCandidate) -> bool:
    """Whether two bands lie on one line and overlap along it (the same rope found twice, e.g.
    at two pyramid levels or in two pieces): not rivals. Ropes on two trunks cannot overlap."""
    u = np.asarray(a.direction, np.float64)
    u = u / max(np.linalg.norm(u), 1e-9)
    v = np.asarray(b.direction, np.float64)
    v = v / max(np.linalg.norm(v), 1e-9)
    if abs(u @ v) < np.cos(np.radians(15)):
        return False
    d = np.asarray(b.center_xy, np.float64) - np.asarray(a.center_xy, np.float64)
    perp = abs(d[0] * u[1] - d[1] * u[0])
    along = abs(d @ u)
    return perp <= max(3.0, 2.0 * (a.thickness_px + b.thickness_px)) and along < 0.5 * (a.length_px + b.length_px)
