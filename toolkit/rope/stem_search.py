"""Mask-guided search for a rope the band detector (:mod:`.band`) missed, and its rope-verifier
glue; imported by the pipeline and the stem-search fitting tools.

A rope far away is thinner than a pixel: its red-ness contrast to the bark (~0.01) is buried in
the pixel noise, and the band detector, which needs a connected thin line, finds nothing. But
the rope crosses its trunk from edge to edge. Averaged across the trunk's width (``n`` pixels,
from the segmenter's instance mask), its contrast stands ``sqrt(n)`` times higher above the
noise. For every segmented tree instance and every tilt in ``tilts_deg`` (camera roll), the
mean red-ness of the instance's pixels is taken per sheared row ``v = y - tan(tilt) (x - x_c)``;
a rope is a row whose mean is above both of its neighbourhoods (2-6 rows above and below).

Each stem's best rows are described by features (:func:`stem_band_features`): the contrast, its
significance against the pixel noise and against the stem's own rows, the trunk width, the
stem's next best row, whether the row's colour shift points towards red (not along the bark's
own colour, not orange), its height above the stem's lowest pixel in trunk widths, and any
faint band the line detector saw there. :attr:`~.config.StemSearchConfig.weights` turns them
into a log-odds score (:func:`stem_band_score`); :func:`trunk_like` requires the row to cross a
trunk, not a crown.

Examples
--------
>>> bands = stem_bands(rgb, instance)              # doctest: +SKIP
>>> det = detect_rope_on_stems(rgb, instance)      # doctest: +SKIP
>>> det.found, det.center_xy                        # doctest: +SKIP
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .config import StemSearchConfig
from .detection import NO_ROPE, RopeCandidate, RopeDetection
from .geometry import instance_at_or_near
from .redness import red_shift_map, redness_map
from .score import linear_score

__all__ = ["StemBand", "stem_bands", "trunk_like", "stem_evidence_choice", "stem_band_features",
           "stem_band_score", "detect_rope_on_stems"]


@dataclass(frozen=True)
class StemBand:
    """A rope hypothesis on one segmented stem (pixels of the image given to :func:`stem_bands`).

    Attributes
    ----------
    tree_id : the instance id.
    center_xy : (x, y) middle of the band on the stem.
    direction : unit (dx, dy) of the band (dx > 0).
    tilt_deg : the band's angle to the image rows.
    width_px : number of instance pixels on the band's row (the trunk's width there).
    contrast : mean red-ness of the row minus the larger of its two neighbourhoods.
    features : values entering :func:`stem_band_score` (with the verifier, also ``stem_score``:
        the logistic score, when ``score`` is the verifier's log-odds).
    score : log-odds that this is the rope.
    polyline : (2, 2) float32 band ends across the instance.
    """
    tree_id: int
    center_xy: tuple[float, float]
    direction: tuple[float, float]
    tilt_deg: float
    width_px: int
    contrast: float
    features: dict = field(default_factory=dict, repr=False)
    score: float = 0.0
    polyline: np.ndarray | None = field(default=None, repr=False)


@dataclass(frozen=True)
class _RowProfile:
    """One stem's rows at one tilt: sheared row index ``v`` (N,) of each pixel (from ``v0``),
    contrast ``c`` (L,), its significance ``z`` (L,), rows wide enough ``ok`` (L,), ``tan(tilt)``."""
    tilt_deg: float
    tn: float
    v0: int
    v: np.ndarray
    c: np.ndarray
    z: np.ndarray
    ok: np.ndarray


def _window_mean(vals: np.ndarray, ok: np.ndarray, lo: int, hi: int):
    """Mean of ``vals`` over valid bins ``i + lo .. i + hi`` for every bin ``i``; NaN when < 3 valid."""
    L = len(vals)
    cv = np.concatenate([[0.0], np.cumsum(np.where(ok, vals, 0.0))])
    cn = np.concatenate([[0], np.cumsum(ok.astype(np.int64))])
    i = np.arange(L)
    a = np.clip(i + lo, 0, L)
    b = np.clip(i + hi + 1, 0, L)
    n = cn[b] - cn[a]
    with np.errstate(invalid="ignore", divide="ignore"):
        m = (cv[b] - cv[a]) / n
    return np.where(n >= 3, m, np.nan)


def stem_band_features(xs: np.ndarray, v: np.ndarray, i: int, c: np.ndarray, zpix: np.ndarray,
                       ok: np.ndarray, rgbs: np.ndarray | None = None, ys: np.ndarray | None = None) -> dict:
    """Features of the band at sheared row ``i`` of one stem.

    Parameters
    ----------
    xs : (N,) x of the stem's pixels.
    v : (N,) their sheared row index (0-based).
    i : the band's row.
    c : (L,) contrast per row; zpix : (L,) its significance against the pixel noise; ok : (L,)
        rows wide enough to count.
    rgbs : (N, 3) float64 the pixels' colours; ys : (N,) their y.

    Returns
    -------
    dict with ``log_contrast``, ``log_zpix``, ``log_zprof`` (against the stem's own rows: how
    unusual this row is on this stem), ``log_width``, ``second`` (the stem's next best
    significance elsewhere over this one), ``runs`` and ``width_change`` (see :func:`trunk_like`);
    with ``rgbs``: ``red_shift`` (cosine of the row's colour change with the direction towards
    red), ``orange`` (the G - B share of that change), ``log_height`` (log of the height above
    the stem's lowest pixel in trunk widths) and its hinges ``h_lo`` (below 2 widths) and
    ``h_hi`` (above 7.4 widths).
    """
    cc = c[ok & np.isfinite(c)]
    med = float(np.median(cc)) if cc.size else 0.0
    mad = float(np.median(np.abs(cc - med))) * 1.4826 if cc.size else 0.0
    zprof = (c[i] - med) / (mad + 0.002)
    row = v == i
    # a trunk crosses the row in one piece, about as wide as just above and below it (branches
    # in a crown cross it in several pieces of varying width)
    xr = np.sort(xs[row])
    runs = 1 + int((np.diff(xr) > 3).sum())
    wn = [int((v == j).sum()) for j in (i - 6, i - 4, i + 4, i + 6)]
    wchg = float(np.log(max(max(wn), 1) / max(min(wn), 1)))
    far = np.abs(np.arange(len(zpix)) - i) > 4
    zo = zpix[far & np.isfinite(zpix)]
    second = float(zo.max()) / max(float(zpix[i]), 1e-6) if zo.size else 0.0
    feats = dict(log_contrast=float(np.log(max(c[i], 1e-4))), log_zpix=float(np.log(max(zpix[i], 1e-3))),
                 log_zprof=float(np.log(np.clip(zprof, 0.1, 60))),
                 log_width=float(np.log(max(int(row.sum()), 1))), second=float(np.clip(second, 0, 2)),
                 runs=runs, width_change=wchg)
    if rgbs is not None:
        feats.update(_colour_features(xs, v, i, row, rgbs, ys))
    return feats


def _colour_features(xs, v, i: int, row, rgbs, ys) -> dict:
    """``red_shift``, ``orange``, ``log_height``, ``h_lo``, ``h_hi`` of :func:`stem_band_features`."""
    x0, x1 = float(xs[row].min()), float(xs[row].max())
    near = np.abs(v - i) <= 6
    # the row's colour shift from its neighbourhood points towards red (a rope mixed into the
    # bark), not along the bark's own colour (a brighter or darker bark texture row)
    nb = near & ~row & (np.abs(v - i) >= 2)
    bg = rgbs[nb].mean(0) if nb.any() else rgbs[row].mean(0)
    dlt = rgbs[row].mean(0) - bg
    d = np.array([190.0, 45.0, 35.0]) - bg
    feats = {"red_shift": float(dlt @ d / (np.linalg.norm(dlt) * np.linalg.norm(d) + 1e-6))}
    # the G - B share of the change: the rope's own G - B against the bark's (orange tape
    # and sand raise it most; its fitted weight is positive: synthetic ropes have G > B)
    feats["orange"] = float((dlt[1] - dlt[2]) / (np.linalg.norm(dlt) + 1e-6))
    # the height above the stem's lowest pixel below the band, in trunk widths (the rope is
    # 1.3 m up a stem some 0.1-0.5 m wide: 2.5-13 widths when the base is seen)
    cols = (xs >= x0) & (xs <= x1)
    ybot = float(ys[cols].max())
    yb = float(ys[row].mean())
    lh = float(np.log(max((ybot - yb) / max(x1 - x0 + 1.0, 1.0), 0.05)))
    feats.update(log_height=lh, h_lo=max(0.0, 0.7 - lh), h_hi=max(0.0, lh - 2.0))
    return feats


def stem_band_score(features: dict, weights: dict | None = None) -> float:
    """Log-odds that a stem band is the rope: ``bias + sum(w_k * features[k])`` over the
    weights' order (:func:`.score.linear_score`; default weights
    :attr:`~.config.StemSearchConfig.weights`)."""
    w = StemSearchConfig().weights if weights is None else weights
    return linear_score(features, w, [k for k in w if k != "bias"])


def stem_bands(rgb: np.ndarray, instance: np.ndarray, *, rope_candidates: list | None = None, near_xy=None,
               per_stem: int | None = None, unclipped_red: bool = False,
               config: StemSearchConfig | None = None) -> list[StemBand]:
    """Rope hypotheses on every segmented stem, best first.

    Parameters
    ----------
    rgb : (H, W, 3) uint8 RGB.
    instance : (H, W) int tree instance ids (0 = none), same pixels.
    rope_candidates : the band detector's scored candidates (:attr:`.detection.RopeDetection.candidates`):
        a faint band it saw at the same place adds evidence (feature ``main``).
    near_xy : (x, y): only the stem under this point (or the nearest one within
        ``pick_stem_radius_frac`` of the photo's width), and only rows within ``near_px`` of it
        (a user's tap on the rope).
    per_stem : how many hypotheses each stem contributes (default: the configuration's).
    unclipped_red : read the rows' mean of :func:`.redness.red_shift_map` instead of the clipped
        :func:`.redness.redness_map` (the rope verifier's search; the logistic weights were
        fitted on the clipped one).
    config : the search's parameters (default :class:`~.config.StemSearchConfig`).

    Returns
    -------
    list of :class:`StemBand`, best score first.
    """
    from scipy import ndimage

    cfg = StemSearchConfig() if config is None else config
    per_stem = cfg.per_stem if per_stem is None else per_stem
    rgb, instance = _checked(rgb, instance)
    F = red_shift_map(rgb) if unclipped_red else redness_map(rgb)
    only = None
    if near_xy is not None:
        only = instance_at_or_near(instance, near_xy, cfg.pick_stem_radius_frac * rgb.shape[1])
        if only == 0:
            return []
    out: list[StemBand] = []
    for k, sl in enumerate(ndimage.find_objects(instance.astype(np.int32))):
        if sl is None or (only is not None and k + 1 != only):
            continue
        out += _bands_of_stem(rgb, instance, F, sl, k + 1, rope_candidates, near_xy, per_stem, cfg)
    out.sort(key=lambda b: -b.score)
    return out


def _checked(rgb, instance):
    """The inputs as arrays, checked: ``(rgb (H, W, 3) uint8, instance (H, W))``."""
    rgb = np.asarray(rgb)
    instance = np.asarray(instance)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    if instance.shape != rgb.shape[:2]:
        raise ValueError(f"instance {instance.shape} does not match the image {rgb.shape[:2]}")
    return rgb, instance


def _bands_of_stem(rgb, instance, F, sl, tid: int, rope_candidates, near_xy, per_stem: int,
                   cfg: StemSearchConfig) -> list[StemBand]:
    """The best bands (on rows at least 5 apart) of stem ``tid`` (bounding slices ``sl``)."""
    sub = instance[sl] == tid
    if int(sub.sum()) < cfg.min_pixels:
        return []
    ys, xs = np.nonzero(sub)
    f = F[sl][ys, xs].astype(np.float64)
    rgbs = rgb[sl][ys, xs].astype(np.float64)
    ys = ys + sl[0].start
    xs = xs + sl[1].start
    xc = float(np.median(xs))
    hyps = []
    for tdeg in cfg.tilts_deg:
        prof = _row_profile(xs, ys, f, xc, tdeg, cfg.min_width_px)
        if prof is not None:
            hyps += _row_hypotheses(prof, xc, near_xy, per_stem * 3, cfg.near_px)
    hyps.sort(key=lambda h: -h[0])
    if near_xy is not None:
        per_stem = max(per_stem, cfg.pick_per_stem)
    H = rgb.shape[0]
    out, taken = [], []
    for _, i, prof in hyps:
        yrow = i + prof.v0                                   # sheared row at x = xc
        if any(abs(yrow - y) < 5 for y in taken):
            continue
        if yrow < cfg.border_px or yrow > H - 1 - cfg.border_px:
            continue                                         # a row cut by the photo's edge
        if near_xy is not None and abs(yrow + prof.tn * (near_xy[0] - xc) - near_xy[1]) > cfg.near_px:
            continue
        out.append(_stem_band(tid, xs, ys, rgbs, xc, i, prof, rope_candidates, cfg.weights))
        taken.append(yrow)
        if len(taken) >= per_stem:
            break
    return out


def _row_profile(xs, ys, f, xc: float, tdeg: float, min_width_px: int) -> _RowProfile | None:
    """The stem's mean red-ness per sheared row at tilt ``tdeg``, its contrast to the rows 2-6
    above and below and that contrast's significance; None when no row is significant."""
    tn = np.tan(np.deg2rad(tdeg))
    vf = ys - tn * (xs - xc)
    v = np.round(vf).astype(np.int64)
    v0 = int(v.min())
    v = v - v0
    n = np.bincount(v)
    s1 = np.bincount(v, f)
    s2 = np.bincount(v, f * f)
    ok = n >= min_width_px
    p = np.where(ok, s1 / np.maximum(n, 1), 0.0)
    var = np.where(ok, np.maximum(s2 / np.maximum(n, 1) - p ** 2, 0.0), 0.0)
    up = _window_mean(p, ok, -6, -2)
    dn = _window_mean(p, ok, 2, 6)
    vloc = _window_mean(var, ok, -6, 6)
    with np.errstate(invalid="ignore"):
        c = np.where(ok, p - np.fmax(up, dn), np.nan)
        c[np.isnan(up) | np.isnan(dn)] = np.nan
        z = c / np.sqrt((vloc + 1e-6) / np.maximum(n, 1))
    if not np.isfinite(z).any():
        return None
    return _RowProfile(tdeg, tn, v0, v, c, z, ok)


def _row_hypotheses(prof: _RowProfile, xc: float, near_xy, count: int, near_px: float) -> list:
    """``(z, row, profile)`` of the ``count`` most significant rows with ``z > 0`` (near a tap:
    within ``near_px`` of it)."""
    z = prof.z
    zz = np.where(np.isfinite(z), z, -np.inf)
    if near_xy is not None:
        v_pick = near_xy[1] - prof.tn * (near_xy[0] - xc) - prof.v0
        zz[np.abs(np.arange(len(zz)) - v_pick) > near_px] = -np.inf
    out = []
    for i in np.argsort(-zz)[:count]:
        if not np.isfinite(zz[i]) or zz[i] <= 0:
            break
        out.append((float(zz[i]), int(i), prof))
    return out


def _stem_band(tid: int, xs, ys, rgbs, xc: float, i: int, prof: _RowProfile, rope_candidates,
               weights: dict) -> StemBand:
    """The scored band of stem ``tid`` at sheared row ``i`` of ``prof``."""
    tn, yrow = prof.tn, i + prof.v0
    feats = stem_band_features(xs, prof.v, i, prof.c, prof.z, prof.ok, rgbs, ys)
    row = prof.v == i
    xl, xr = float(xs[row].min()), float(xs[row].max())
    feats["main"] = _main_evidence(rope_candidates, 0.5 * (xl + xr), yrow + tn * (0.5 * (xl + xr) - xc),
                                   int(row.sum()))
    d = np.array([1.0, tn]) / np.hypot(1.0, tn)
    pl = np.array([[xl, yrow + tn * (xl - xc)], [xr, yrow + tn * (xr - xc)]], np.float32)
    xm = 0.5 * (xl + xr)
    return StemBand(tid, (xm, float(yrow + tn * (xm - xc))), (float(d[0]), float(d[1])), float(prof.tilt_deg),
                    int(row.sum()), float(prof.c[i]), feats, stem_band_score(feats, weights), pl)


def trunk_like(band: StemBand, config: StemSearchConfig | None = None) -> bool:
    """Whether the band's row crosses a trunk (at most ``max_runs`` pieces of near-constant
    width, within ``max_width_change``), not a crown."""
    cfg = StemSearchConfig() if config is None else config
    return (band.features.get("runs", 1) <= cfg.max_runs
            and band.features.get("width_change", 0.0) <= cfg.max_width_change)


def _main_evidence(cands, x: float, y: float, width: int) -> float:
    """The band detector's best score at ``(x, y)`` (clipped to [-6, 4], shifted by +6); 0 if none there."""
    best = None
    for c in cands or ():
        if abs(c.center_xy[1] - y) < 6 + c.thickness_px and abs(c.center_xy[0] - x) < max(10, width):
            best = c.score if best is None else max(best, c.score)
    return 0.0 if best is None else float(np.clip(best, -6, 4)) + 6.0


def stem_evidence_choice(rgb: np.ndarray, instance: np.ndarray, points, *, rope_candidates=None,
                         config: StemSearchConfig | None = None) -> int | None:
    """Which of several rope candidates lies on a stem with a rope-like band there, if just one.

    For each point (x, y) the best trunk-like stem band within a few rows of it is scored
    (:func:`stem_bands` with ``near_xy``). Returns the index of the one point whose band scores
    above ``min_score`` while every other scores below ``min_score - evidence_margin`` (or has
    none), else None. The pipeline uses it when the band detector finds two ropes alike.

    Parameters
    ----------
    rgb : (H, W, 3) uint8; instance : (H, W) int tree instance ids.
    points : sequence of (x, y) candidate centres.
    rope_candidates : the band detector's candidates (see :func:`stem_bands`).
    config : the search's parameters (default :class:`~.config.StemSearchConfig`).
    """
    cfg = StemSearchConfig() if config is None else config
    scores = []
    for xy in points:
        bands = [b for b in stem_bands(rgb, instance, near_xy=tuple(map(float, xy)), rope_candidates=rope_candidates,
                                       config=cfg) if trunk_like(b, cfg)]
        scores.append(max((b.score for b in bands), default=-np.inf))
    good = [i for i, sc in enumerate(scores) if sc > cfg.min_score]
    if len(good) != 1:
        return None
    if any(sc >= cfg.min_score - cfg.evidence_margin for i, sc in enumerate(scores) if i != good[0]):
        return None
    return good[0]


def _verified_bands(rgb, instance, rope_candidates, verifier, cfg: StemSearchConfig) -> list[StemBand]:
    """Trunk-like stem bands (unclipped red-ness) scored by the verifier's log-odds, best first;
    the logistic score is kept in ``features["stem_score"]``."""
    bands = [b for b in stem_bands(rgb, instance, rope_candidates=rope_candidates, per_stem=cfg.verifier_per_stem,
                                   unclipped_red=True, config=cfg) if trunk_like(b, cfg)]
    masks: dict[int, np.ndarray] = {}
    for b in bands:
        if b.tree_id not in masks:
            masks[b.tree_id] = instance == b.tree_id
    z = verifier.logits(rgb, [masks[b.tree_id] for b in bands], bands)
    out = [replace(b, score=float(zi), features={**b.features, "stem_score": b.score}) for b, zi in zip(bands, z)]
    out.sort(key=lambda b: -b.score)
    return out


def detect_rope_on_stems(rgb: np.ndarray, instance: np.ndarray, *, pick_xy=None, rope_candidates=None,
                         verifier=None, config: StemSearchConfig | None = None) -> RopeDetection:
    """The rope as the best stem band (:func:`stem_bands`), in the form :func:`.band.detect_rope` gives.

    Parameters
    ----------
    rgb : (H, W, 3) uint8 RGB.
    instance : (H, W) int tree instance ids.
    pick_xy : (x, y): a user's tap on the rope: the best band on the stem under it within a few
        pixels of it, scoring above ``pick_min_score``, instead of the best band in the photo.
    rope_candidates : the band detector's candidates (see :func:`stem_bands`).
    verifier : optional :class:`monodbh.models.runtime.rope_verifier.RopeVerifier`: without a tap, the
        bands are scored by it instead (log-odds above ``verifier_min_logit``, ambiguous within
        ``verifier_margin``; ``score`` is then its log-odds).
    config : the search's parameters (default :class:`~.config.StemSearchConfig`): the best
        band must score above ``min_score``; one on another stem within ``ambiguity_margin``
        of it makes the result ambiguous.

    Returns
    -------
    RopeDetection
        falsy with a reason when no band qualifies. ``thickness_px`` is 1 (the rope is thinner
        than the profile can resolve), ``mask`` the band's row across the stem.
    """
    cfg = StemSearchConfig() if config is None else config
    if verifier is not None and pick_xy is None:
        bands = _verified_bands(rgb, instance, rope_candidates, verifier, cfg)
        min_score, margin = cfg.verifier_min_logit, cfg.verifier_margin
    else:
        bands = stem_bands(rgb, instance, rope_candidates=rope_candidates, near_xy=pick_xy, config=cfg)
        min_score, margin = cfg.min_score, cfg.ambiguity_margin
    cands = [RopeCandidate(center_xy=b.center_xy, direction=b.direction,
                           length_px=float(np.linalg.norm(b.polyline[1] - b.polyline[0])), thickness_px=1.0,
                           score=b.score, contrast=b.contrast, polyline=b.polyline, features=b.features)
             for b in bands]
    best = _chosen_band(bands, cands, pick_xy, min_score, margin, cfg)
    if isinstance(best, RopeDetection):
        return best
    return RopeDetection(True, "", center_xy=best.center_xy, direction=best.direction, polyline=best.polyline,
                         thickness_px=1.0, mask=_row_mask(best, instance), score=best.score, candidates=cands)


def _chosen_band(bands, cands, pick_xy, min_score: float, margin: float, cfg: StemSearchConfig):
    """The band to report, or the failed :class:`RopeDetection` (none qualifies, or ambiguous)."""
    if pick_xy is not None:
        good = [b for b in bands if b.score > cfg.pick_min_score and b.features["log_zpix"] >= np.log(cfg.pick_min_zpix)]
        if not good:
            return RopeDetection(False, f"no red rope found at the picked point ({pick_xy[0]:.0f},{pick_xy[1]:.0f})",
                                 candidates=cands)
        return good[0]
    good = [b for b in bands if b.score > min_score and trunk_like(b, cfg)]
    if not good:
        return RopeDetection(False, NO_ROPE, candidates=cands)
    best = good[0]
    rivals = [b for b in good[1:] if b.tree_id != best.tree_id and b.score > best.score - margin]
    if rivals:
        r = rivals[0]
        return RopeDetection(False, f"two rope candidates at ({best.center_xy[0]:.0f},{best.center_xy[1]:.0f}) "
                                    f"and ({r.center_xy[0]:.0f},{r.center_xy[1]:.0f}) (e.g. two roped trees): "
                                    f"--pick X,Y to choose one", candidates=cands, ambiguous=True)
    return best


def _row_mask(band: StemBand, instance: np.ndarray) -> np.ndarray:
    """(H, W) bool: the band's row across its stem."""
    H, W = instance.shape
    mask = np.zeros((H, W), bool)
    xl, xr = band.polyline[:, 0]
    xx = np.arange(int(np.floor(xl)), int(np.ceil(xr)) + 1)
    yy = np.interp(xx, band.polyline[:, 0], band.polyline[:, 1])
    keep = (xx >= 0) & (xx < W) & (yy >= 0) & (yy < H - 0.5)
    mask[np.round(yy[keep]).astype(int), xx[keep]] = True
    mask &= instance == band.tree_id
    return mask
