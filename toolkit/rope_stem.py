"""Mask-guided search for a rope the band detector (:mod:`.rope`) missed; imported by the pipeline.

A rope far away is thinner than a pixel: its red-ness contrast to the bark (~0.01) is buried in
the pixel noise, and the band detector, which needs a connected thin line, finds nothing. But
the rope crosses its trunk from edge to edge. Averaged across the trunk's width (``n`` pixels,
from the segmenter's instance mask), its contrast stands ``sqrt(n)`` times higher above the
noise. For every segmented tree instance and every tilt in ``tilts_deg`` (camera roll), the
mean red-ness of the instance's pixels is taken per sheared row ``v = y - tan(tilt) (x - x_c)``;
a rope is a row whose mean is above both of its neighbourhoods (2-6 rows above and below).

Each stem's best rows are described by features (:func:`band_features`): the contrast, its
significance against the pixel noise and against the stem's own rows, the trunk width, the
stem's next best row, whether the row's colour shift points towards red (not along the bark's
own colour, not orange), its height above the stem's lowest pixel in trunk widths, and any
faint band the line detector saw there. :data:`STEM_WEIGHTS` turns them into a log-odds score
(a logistic fit on the calibration sets, seeds 9100 and 9200); :func:`trunk_like` requires the
row to cross a trunk, not a crown. Measured on the benchmark (seed 9000) and on the 24 real
rope-free photos: see ``docs/decisions/stem-search.md``.

Examples
--------
>>> bands = stem_bands(rgb, instance)              # doctest: +SKIP
>>> det = detect_rope_on_stems(rgb, instance)      # doctest: +SKIP
>>> det.found, det.center_xy                        # doctest: +SKIP
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .rope import RopeCandidate, RopeDetection, red_shift_map, redness_map

__all__ = ["StemBand", "stem_bands", "trunk_like", "stem_evidence_choice", "band_features", "stem_band_score", "detect_rope_on_stems", "VERIFIER_PER_STEM", "VERIFIER_MIN_LOGIT", "VERIFIER_MARGIN",
           "STEM_WEIGHTS", "STEM_MIN_SCORE", "STEM_PICK_MIN_SCORE"]


@dataclass
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
    features : values entering :func:`stem_band_score`.
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


def band_features(xs: np.ndarray, v: np.ndarray, i: int, c: np.ndarray, zpix: np.ndarray,
                  ok: np.ndarray, rgbs: np.ndarray | None = None, ys: np.ndarray | None = None) -> dict:
    """Features of the band at sheared row ``i`` of one stem.

    Parameters
    ----------
    xs : (N,) x of the stem's pixels.
    v : (N,) their sheared row index (0-based).
    i : the band's row.
    c : (L,) contrast per row; zpix : (L,) its significance against the pixel noise; ok : (L,)
        rows wide enough to count.

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
    x0, x1 = float(xs[row].min()), float(xs[row].max())
    near = np.abs(v - i) <= 6
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
        # the row's colour shift from its neighbourhood points towards red (a rope mixed into the
        # bark), not along the bark's own colour (a brighter or darker bark texture row)
        nb = near & ~row & (np.abs(v - i) >= 2)
        bg = rgbs[nb].mean(0) if nb.any() else rgbs[row].mean(0)
        dlt = rgbs[row].mean(0) - bg
        d = np.array([190.0, 45.0, 35.0]) - bg
        feats["red_shift"] = float(dlt @ d / (np.linalg.norm(dlt) * np.linalg.norm(d) + 1e-6))
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


#: logistic weights of :func:`stem_band_score` (``python -m monodbh.toolkit.fit_rope_stem``;
#: calibration sets seeds 9100 + 9200, 4392 bands of which 159 on the true rope).
STEM_WEIGHTS = {"bias": -8.57, "log_contrast": 0.637, "log_zpix": 1.043, "log_zprof": 0.427, "log_width": 1.274,
                "second": 0.306, "red_shift": 1.023, "h_lo": -1.169, "h_hi": -1.058, "main": 0.44, "orange": 1.11}

#: a stem band scoring above this (and :func:`trunk_like`) is accepted as the rope when the band
#: detector found none. Set on the calibration sets (seeds 9100 + 9200): of their 40 roped photos
#: where the band detector found no rope, the best trunk-like band is the rope and above -1 in
#: 11, a wrong band above -1 in 2; on 47 rope-free photos (16 + 10 benchmark + 21 real ones with
#: stems) only an orange flagging tape (1.0) scores above -1.67 (``fit_rope_stem``).
STEM_MIN_SCORE = -1.0
#: ... and above this one where the user tapped the rope (``--pick``), standing out of the pixel
#: noise by 2 standard errors. Measured on the benchmark (seed 9000): a tap on each of the 23
#: ropes neither detector found is accepted in 12 (9 at -3, 15 at -5); taps at 324 random stem
#: points away from the rope are accepted in 33 (10 %; 2.8 % at -3, 22 % at -5): a tap off the
#: rope is mostly an error, and a band accepted there is flagged ``rope_from_stem_profile``.
STEM_PICK_MIN_SCORE = -4.0
STEM_PICK_MIN_ZPIX = 2.0


def stem_band_score(features: dict, weights: dict | None = None) -> float:
    """Log-odds that a stem band is the rope: ``bias + sum(w_k * features[k])``."""
    w = STEM_WEIGHTS if weights is None else weights
    return float(w.get("bias", 0.0) + sum(w[k] * features[k] for k in w if k != "bias"))


def stem_bands(rgb: np.ndarray, instance: np.ndarray, *, tilts_deg=tuple(range(-15, 16, 3)),
               min_pixels: int = 150, min_width_px: int = 5, per_stem: int = 2, border_px: int = 8,
               rope_candidates: list | None = None, near_xy=None, near_px: float = 8.0,
               weights: dict | None = None, unclipped_red: bool = False) -> list[StemBand]:
    """Rope hypotheses on every segmented stem, best first.

    Parameters
    ----------
    rgb : (H, W, 3) uint8 RGB.
    instance : (H, W) int tree instance ids (0 = none), same pixels.
    tilts_deg : band angles to the image rows that are tried.
    min_pixels : instances smaller than this are skipped.
    min_width_px : a row counts when at least this many instance pixels lie on it.
    per_stem : how many hypotheses (on different rows) each stem contributes.
    border_px : rows this close to the top or bottom of the photo are not bands.
    rope_candidates : the band detector's scored candidates (:attr:`.rope.RopeDetection.candidates`):
        a faint band it saw at the same place adds evidence (feature ``main``).
    near_xy : (x, y): only the stem under this point (or the nearest one within 3 % of the
        photo's width), and only rows within ``near_px`` of it (a user's tap on the rope).
    weights : override :data:`STEM_WEIGHTS`.
    unclipped_red : read the rows' mean of :func:`.rope.red_shift_map` instead of the clipped
        :func:`.rope.redness_map` (the rope verifier's search; :data:`STEM_WEIGHTS` were fitted
        on the clipped one).

    Returns
    -------
    list of :class:`StemBand`, best score first.
    """
    from scipy import ndimage

    rgb = np.asarray(rgb)
    instance = np.asarray(instance)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    if instance.shape != rgb.shape[:2]:
        raise ValueError(f"instance {instance.shape} does not match the image {rgb.shape[:2]}")
    F = red_shift_map(rgb) if unclipped_red else redness_map(rgb)
    H = rgb.shape[0]
    out: list[StemBand] = []
    objs = ndimage.find_objects(instance.astype(np.int32))
    only = None
    if near_xy is not None:
        only = _stem_near(instance, near_xy, 0.03 * rgb.shape[1])
        if only == 0:
            return []
    for k, sl in enumerate(objs):
        if sl is None or (only is not None and k + 1 != only):
            continue
        tid = k + 1
        sub = instance[sl] == tid
        if int(sub.sum()) < min_pixels:
            continue
        ys, xs = np.nonzero(sub)
        f = F[sl][ys, xs].astype(np.float64)
        rgbs = rgb[sl][ys, xs].astype(np.float64)
        ys = ys + sl[0].start
        xs = xs + sl[1].start
        xc = float(np.median(xs))
        hyps = []
        for tdeg in tilts_deg:
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
                continue
            zz = np.where(np.isfinite(z), z, -np.inf)
            if near_xy is not None:
                v_pick = near_xy[1] - tn * (near_xy[0] - xc) - v0
                zz[np.abs(np.arange(len(zz)) - v_pick) > near_px] = -np.inf
            for i in np.argsort(-zz)[:per_stem * 3]:
                if not np.isfinite(zz[i]) or zz[i] <= 0:
                    break
                hyps.append((float(zz[i]), tdeg, int(i), v0, v, c, z, ok, tn))
        hyps.sort(key=lambda h: -h[0])
        taken: list[tuple[float, float]] = []
        if near_xy is not None:
            per_stem = max(per_stem, 3)
        for zi, tdeg, i, v0, v, c, z, ok, tn in hyps:
            yrow = i + v0                                    # sheared row at x = xc
            if any(abs(yrow - y) < 5 for y, _ in taken):
                continue
            if yrow < border_px or yrow > H - 1 - border_px:
                continue                                     # a row cut by the photo's edge
            if near_xy is not None and abs(yrow + tn * (near_xy[0] - xc) - near_xy[1]) > near_px:
                continue
            feats = band_features(xs, v, i, c, z, ok, rgbs, ys)
            row = v == i
            xl, xr = float(xs[row].min()), float(xs[row].max())
            feats["main"] = _main_evidence(rope_candidates, 0.5 * (xl + xr), yrow + tn * (0.5 * (xl + xr) - xc),
                                           int(row.sum()))
            d = np.array([1.0, tn]) / np.hypot(1.0, tn)
            pl = np.array([[xl, yrow + tn * (xl - xc)], [xr, yrow + tn * (xr - xc)]], np.float32)
            xm = 0.5 * (xl + xr)
            b = StemBand(tid, (xm, float(yrow + tn * (xm - xc))), (float(d[0]), float(d[1])), float(tdeg),
                         int(row.sum()), float(c[i]), feats, stem_band_score(feats, weights), pl)
            taken.append((yrow, b.score))
            out.append(b)
            if len(taken) >= per_stem:
                break
    out.sort(key=lambda b: -b.score)
    return out


#: a band is on a trunk when the instance crosses its row in at most this many pieces ...
STEM_MAX_RUNS = 1
#: ... and the instance's width 4-6 rows above and below it varies by at most this log ratio
STEM_MAX_WIDTH_CHANGE = 0.4


def trunk_like(band: StemBand) -> bool:
    """Whether the band's row crosses a trunk (one piece of near-constant width), not a crown.

    Measured (docs/decisions/stem-search.md): of 278 true rope bands on the calibration sets and the benchmark, 5
    cross in two pieces and 6 where the width changes more; of the 4 best false bands on the 24
    real rope-free photos, all fail (crown branches).
    """
    return band.features.get("runs", 1) <= STEM_MAX_RUNS and band.features.get("width_change", 0.0) <= STEM_MAX_WIDTH_CHANGE


def _stem_near(instance: np.ndarray, xy, radius: float) -> int:
    """The instance id under ``xy``, else the most frequent one within ``radius`` pixels; 0 if none."""
    H, W = instance.shape
    x, y = int(np.clip(round(xy[0]), 0, W - 1)), int(np.clip(round(xy[1]), 0, H - 1))
    if instance[y, x] > 0:
        return int(instance[y, x])
    r = int(max(2, round(radius)))
    win = instance[max(0, y - r):y + r + 1, max(0, x - r):x + r + 1]
    ids = win[win > 0]
    return int(np.bincount(ids).argmax()) if ids.size else 0


def _main_evidence(cands, x: float, y: float, width: int) -> float:
    """The band detector's best score at ``(x, y)`` (clipped to [-6, 4], shifted by +6); 0 if none there."""
    best = None
    for c in cands or ():
        if abs(c.center_xy[1] - y) < 6 + c.thickness_px and abs(c.center_xy[0] - x) < max(10, width):
            best = c.score if best is None else max(best, c.score)
    return 0.0 if best is None else float(np.clip(best, -6, 4)) + 6.0


def stem_evidence_choice(rgb: np.ndarray, instance: np.ndarray, points, *, rope_candidates=None,
                         min_score: float = STEM_MIN_SCORE, margin: float = 2.0) -> int | None:
    """Which of several rope candidates lies on a stem with a rope-like band there, if just one.

    For each point (x, y) the best trunk-like stem band within a few rows of it is scored
    (:func:`stem_bands` with ``near_xy``). Returns the index of the one point whose band scores
    above ``min_score`` while every other scores below ``min_score - margin`` (or has none),
    else None. The pipeline uses it when the band detector finds two ropes alike. Measured
    (docs/decisions/stem-search.md): of the 280 calibration and benchmark photos, 2 were ambiguous; in both, the
    true rope's band scored 1.5-1.6 and the rival's -3.7 or had none.

    Parameters
    ----------
    rgb : (H, W, 3) uint8; instance : (H, W) int tree instance ids.
    points : sequence of (x, y) candidate centres.
    """
    scores = []
    for xy in points:
        bands = [b for b in stem_bands(rgb, instance, near_xy=tuple(map(float, xy)), rope_candidates=rope_candidates)
                 if trunk_like(b)]
        scores.append(max((b.score for b in bands), default=-np.inf))
    good = [i for i, sc in enumerate(scores) if sc > min_score]
    if len(good) != 1:
        return None
    if any(sc >= min_score - margin for i, sc in enumerate(scores) if i != good[0]):
        return None
    return good[0]


#: with the rope verifier (``monodbh.models.runtime_rope``): bands per stem it is shown (as in
#: its training banks), the log-odds it needs, and the margin below the best within which a band
#: on another stem makes the answer ambiguous. Set on the calibration sets (seeds 9100-9400,
#: never used to train it): see ``docs/decisions/rope-verifier.md``.
VERIFIER_PER_STEM = 4
VERIFIER_MIN_LOGIT = 3.0
VERIFIER_MARGIN = 1.0


def _verified_bands(rgb, instance, rope_candidates, verifier) -> list[StemBand]:
    """Trunk-like stem bands (unclipped red-ness) scored by the verifier's log-odds, best first;
    the logistic score is kept in ``features["stem_score"]``."""
    bands = [b for b in stem_bands(rgb, instance, rope_candidates=rope_candidates, per_stem=VERIFIER_PER_STEM,
                                   unclipped_red=True) if trunk_like(b)]
    masks: dict[int, np.ndarray] = {}
    for b in bands:
        if b.tree_id not in masks:
            masks[b.tree_id] = instance == b.tree_id
    z = verifier.logits(rgb, [masks[b.tree_id] for b in bands], bands)
    for b, zi in zip(bands, z):
        b.features["stem_score"] = b.score
        b.score = float(zi)
    bands.sort(key=lambda b: -b.score)
    return bands


def detect_rope_on_stems(rgb: np.ndarray, instance: np.ndarray, *, pick_xy=None, rope_candidates=None,
                         min_score: float = STEM_MIN_SCORE, pick_min_score: float = STEM_PICK_MIN_SCORE,
                         ambiguity_margin: float = 1.0, weights: dict | None = None,
                         verifier=None) -> RopeDetection:
    """The rope as the best stem band (:func:`stem_bands`), in the form :func:`.rope.detect_rope` gives.

    Parameters
    ----------
    rgb : (H, W, 3) uint8 RGB.
    instance : (H, W) int tree instance ids.
    pick_xy : (x, y): a user's tap on the rope: the best band on the stem under it within a few
        pixels of it, scoring above ``pick_min_score``, instead of the best band in the photo.
    rope_candidates : the band detector's candidates (see :func:`stem_bands`).
    min_score : the best band must score above this.
    pick_min_score : ... or above this one at a user's tap.
    ambiguity_margin : a band on another stem within this margin of the best makes the result
        ambiguous (``found=False``, ``ambiguous=True``).
    verifier : optional :class:`monodbh.models.runtime_rope.RopeVerifier`: without a tap, the
        bands are scored by it instead (log-odds above :data:`VERIFIER_MIN_LOGIT`, ambiguous
        within :data:`VERIFIER_MARGIN`; ``score`` is then its log-odds).

    Returns
    -------
    RopeDetection
        falsy with a reason when no band qualifies. ``thickness_px`` is 1 (the rope is thinner
        than the profile can resolve), ``mask`` the band's row across the stem.
    """
    if verifier is not None and pick_xy is None:
        bands = _verified_bands(rgb, instance, rope_candidates, verifier)
        min_score, ambiguity_margin = VERIFIER_MIN_LOGIT, VERIFIER_MARGIN
    else:
        bands = stem_bands(rgb, instance, weights=weights, rope_candidates=rope_candidates, near_xy=pick_xy)
    cands = [RopeCandidate(center_xy=b.center_xy, direction=b.direction,
                           length_px=float(np.linalg.norm(b.polyline[1] - b.polyline[0])), thickness_px=1.0,
                           score=b.score, contrast=b.contrast, polyline=b.polyline, features=b.features)
             for b in bands]
    if pick_xy is not None:
        good = [b for b in bands if b.score > pick_min_score and b.features["log_zpix"] >= np.log(STEM_PICK_MIN_ZPIX)]
        if not good:
            return RopeDetection(False, f"no red rope found at the picked point ({pick_xy[0]:.0f},{pick_xy[1]:.0f})",
                                 candidates=cands)
        best = good[0]
    else:
        good = [b for b in bands if b.score > min_score and trunk_like(b)]
        if not good:
            return RopeDetection(False, "no red rope found (no thin red band across a trunk)", candidates=cands)
        best = good[0]
        rivals = [b for b in good[1:] if b.tree_id != best.tree_id and b.score > best.score - ambiguity_margin]
        if rivals:
            r = rivals[0]
            return RopeDetection(False, f"two rope candidates at ({best.center_xy[0]:.0f},{best.center_xy[1]:.0f}) "
                                        f"and ({r.center_xy[0]:.0f},{r.center_xy[1]:.0f}) (e.g. two roped trees): "
                                        f"--pick X,Y to choose one", candidates=cands, ambiguous=True)
    H, W = instance.shape
    mask = np.zeros((H, W), bool)
    xl, xr = best.polyline[:, 0]
    xx = np.arange(int(np.floor(xl)), int(np.ceil(xr)) + 1)
    yy = np.interp(xx, best.polyline[:, 0], best.polyline[:, 1])
    keep = (xx >= 0) & (xx < W) & (yy >= 0) & (yy < H - 0.5)
    mask[np.round(yy[keep]).astype(int), xx[keep]] = True
    mask &= instance == best.tree_id
    return RopeDetection(True, "", center_xy=best.center_xy, direction=best.direction, polyline=best.polyline,
                         thickness_px=1.0, mask=mask, score=best.score, candidates=cands)
