"""The rope from the mask-free rope finder network's candidates, and the finder's cross-check of
a rope the classical detectors found; imported by the pipeline and the finder's fitting tool.

The finder (``monodbh.models.runtime.rope_finder``, kind ``rope_finder``) marks rope pixels over the whole
working image; its candidates are connected pieces of them (:class:`~monodbh.models.runtime.rope_finder.RopeComponent`).
The pipeline asks it only where the band detector (:mod:`.band`) and the mask-guided stem
search (:mod:`.stem_search`) found no rope. A candidate is the rope when it is confident (peak
log-odds and summed probability above :class:`~.config.FinderConfig`'s ``min_peak`` and
``min_mass``), band-shaped (:func:`band_shaped`: long against its thickness, and across the stem,
so a vertical paint mark or hanging rope end is no band), and no other candidate comes close
(``rival_share`` of its mass: two roped trees, or a rope and a red thing the finder cannot tell
apart, then the user picks).

Examples
--------
>>> from monodbh.models.runtime.rope_finder import rope_components
>>> z = np.full((100, 100), -8.0, np.float32); z[50, 20:70] = 6.0
>>> det = rope_from_finder(rope_components(z), (200, 200))
>>> det.found, [round(v) for v in det.center_xy]
(True, [90, 100])
"""
from __future__ import annotations

import numpy as np

from .config import FinderConfig
from .detection import NO_ROPE, RopeDetection
from .geometry import distance_to_chord

__all__ = ["band_shaped", "rope_from_finder", "finder_support", "finder_check"]


def band_shaped(c, config: FinderConfig | None = None) -> bool:
    """Is candidate ``c`` a band across a stem (at least ``min_elongation`` thicknesses and
    ``min_length_px`` long, not steeper than ``max_tilt_deg``)?"""
    cfg = FinderConfig() if config is None else config
    tilt = np.degrees(np.arctan2(abs(float(c.direction[1])), abs(float(c.direction[0])) + 1e-12))
    return (c.length_px >= cfg.min_elongation * c.thickness_px and c.length_px >= cfg.min_length_px
            and tilt <= cfg.max_tilt_deg)


def rope_from_finder(components, shape: tuple[int, int], *, pick_xy=None, min_peak: float | None = None,
                     min_mass: float | None = None, rival_share: float | None = None,
                     config: FinderConfig | None = None) -> RopeDetection:
    """The rope as :func:`.band.detect_rope` gives it, from the finder's ``components`` (best first).

    Parameters
    ----------
    components : list of RopeComponent, photo pixels of an image of ``shape`` = (H, W).
    pick_xy : (x, y) a user's tap on the rope: the best candidate within ``pick_radius_px`` of
        it above the pick thresholds, no rival rule.
    min_peak, min_mass, rival_share : this call's acceptance rule instead of the configuration's.
    config : the acceptance parameters (default :class:`~.config.FinderConfig`).

    Returns
    -------
    RopeDetection : found, or not (``ambiguous`` when two candidates qualify), with the reason.
    """
    cfg = FinderConfig() if config is None else config
    min_peak = cfg.min_peak if min_peak is None else min_peak
    min_mass = cfg.min_mass if min_mass is None else min_mass
    rival_share = cfg.rival_share if rival_share is None else rival_share
    if pick_xy is not None:
        good = [c for c in components if band_shaped(c, cfg) and c.peak >= cfg.pick_min_peak
                and c.mass >= cfg.pick_min_mass and distance_to_chord(c.polyline, pick_xy) <= cfg.pick_radius_px]
        if not good:
            return RopeDetection(False, f"no red rope found at the picked point ({pick_xy[0]:.0f},{pick_xy[1]:.0f})")
        good.sort(key=lambda c: distance_to_chord(c.polyline, pick_xy))
        best, rivals = good[0], []
    else:
        good = [c for c in components if band_shaped(c, cfg) and c.peak >= min_peak and c.mass >= min_mass]
        if not good:
            return RopeDetection(False, NO_ROPE)
        best = good[0]
        rivals = [c for c in components if c is not best and band_shaped(c, cfg) and c.peak >= min_peak
                  and c.mass >= rival_share * best.mass]
    if rivals:
        r = rivals[0]
        return RopeDetection(False, f"two rope candidates at ({best.center_xy[0]:.0f},{best.center_xy[1]:.0f}) "
                                    f"and ({r.center_xy[0]:.0f},{r.center_xy[1]:.0f}) (e.g. two roped trees): "
                                    f"--pick X,Y to choose one", ambiguous=True)
    return _band_detection(best, shape)


def _band_detection(best, shape: tuple[int, int]) -> RopeDetection:
    """The found rope of candidate ``best``: its straight centre line left to right, sampled
    every pixel, and those pixels as the mask."""
    H, W = shape
    poly = np.asarray(best.polyline, np.float32)
    if poly[0, 0] > poly[-1, 0]:
        poly = poly[::-1].copy()
    n = max(2, int(np.ceil(np.hypot(*(poly[-1] - poly[0])))) + 1)
    pts = poly[0] + np.linspace(0.0, 1.0, n)[:, None] * (poly[-1] - poly[0])
    mask = np.zeros((H, W), bool)
    xi, yi = np.floor(pts[:, 0] + 0.5).astype(int), np.floor(pts[:, 1] + 0.5).astype(int)
    keep = (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
    mask[yi[keep], xi[keep]] = True
    return RopeDetection(True, "", center_xy=best.center_xy, direction=best.direction, polyline=pts.astype(np.float32),
                         thickness_px=float(best.thickness_px), mask=mask, score=float(best.peak))


def finder_support(components, xy, config: FinderConfig | None = None) -> float:
    """The highest log-odds of the finder candidates passing near ``xy`` (``-inf`` when none).

    Near: within ``max(support_radius_px, thickness / 2 + 4)`` photo pixels of the candidate's
    centre line (:func:`.geometry.distance_to_chord`).
    """
    cfg = FinderConfig() if config is None else config
    near = [c.peak for c in components
            if distance_to_chord(c.polyline, xy) <= max(cfg.support_radius_px, 0.5 * c.thickness_px + 4.0)]
    return float(max(near)) if near else float("-inf")


def finder_check(rope, components, shape: tuple[int, int], whole=None,
                 config: FinderConfig | None = None) -> tuple[str, RopeDetection | None]:
    """The rope finder's verdict on a rope found by the classical detectors.

    The band detector can take a red band that is no rope (tape on another tree, red leaves,
    a jacket's edge) where the real rope is faint to it, and the stem search a red row of bark.
    The finder, trained with such distractors, marks nearly every rope those two find, thin
    ones included, and is rarely wrong when it is confident. So:

    - ``("supported", None)``: a finder candidate passes through the rope
      (:func:`finder_support` >= ``support_min_peak``): keep it;
    - ``("replaced", det)``: no support, and the finder accepts a band of its own elsewhere
      (:func:`rope_from_finder`, the shipped rule): that band is the rope;
    - ``("unsupported", None)``: no support and no band of the finder's: the band is no rope
      as far as the photo shows (the user can still tap it: ``--pick`` skips this check).

    Parameters
    ----------
    rope : RopeDetection found by the band detector or the stem search (working-image pixels).
    components : the finder's candidates on the same image (or on one tile around the rope,
        :meth:`~monodbh.models.runtime.rope_finder.RopeFinder.components_near`), best first.
    shape : (H, W) of the image.
    whole : optional callable returning the candidates of the whole image, called only when
        ``components`` do not support the rope (the finder's own band may be anywhere).
    config : the acceptance parameters (default :class:`~.config.FinderConfig`).

    Returns
    -------
    (verdict, RopeDetection or None)

    Examples
    --------
    >>> from monodbh.models.runtime.rope_finder import rope_components
    >>> z = np.full((100, 100), -8.0, np.float32); z[50, 20:70] = 8.0       # the finder's rope
    >>> tape = RopeDetection(True, "", center_xy=(90.0, 20.0), direction=(1.0, 0.0))
    >>> verdict, alt = finder_check(tape, rope_components(z), (200, 200))
    >>> verdict, [round(v) for v in alt.center_xy]
    ('replaced', [90, 100])
    >>> finder_check(alt, rope_components(z), (200, 200))[0]
    'supported'
    >>> finder_check(tape, [], (200, 200))[0]
    'unsupported'
    """
    cfg = FinderConfig() if config is None else config
    if finder_support(components, rope.center_xy, cfg) >= cfg.support_min_peak:
        return "supported", None
    alt = rope_from_finder(whole() if whole is not None else components, shape, config=cfg)
    if alt:
        return "replaced", alt
    return "unsupported", None
