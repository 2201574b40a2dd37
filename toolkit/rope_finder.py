"""The rope from the mask-free rope finder's candidates; imported by the pipeline.

The finder (``monodbh.models.runtime_ropeseg``, kind ``ropeseg``) marks rope pixels over the whole
working image; its candidates are connected pieces of them (:class:`~monodbh.models.runtime_ropeseg.RopeComponent`).
The pipeline asks it only where the band detector (:mod:`.rope`) and the mask-guided stem
search (:mod:`.rope_stem`) found no rope. A candidate is the rope when it is confident
(peak log-odds >= :data:`FINDER_MIN_PEAK` and summed probability >= :data:`FINDER_MIN_MASS`,
about that many output pixels of 2 x 2 photo pixels), band-shaped (length >=
:data:`FINDER_MIN_ELONGATION` thicknesses and >= :data:`FINDER_MIN_LENGTH_PX`, and across the
stem: within :data:`FINDER_MAX_TILT_DEG` of horizontal, so a vertical paint mark or hanging
rope end is no band), and no other
candidate comes close (:data:`FINDER_RIVAL_SHARE` of its mass: two roped trees, or a rope and a
red thing the finder cannot tell apart, then the user picks). Thresholds chosen on the
calibration sets (seeds 9100-9600), see ``docs/decisions/rope-finder.md``.

Examples
--------
>>> from monodbh.models.runtime_ropeseg import rope_components
>>> z = np.full((100, 100), -8.0, np.float32); z[50, 20:70] = 6.0
>>> det = rope_from_finder(rope_components(z), (200, 200))
>>> det.found, [round(v) for v in det.center_xy]
(True, [90, 100])
"""
from __future__ import annotations

import numpy as np

from .rope import RopeDetection

__all__ = ["FINDER_MIN_PEAK", "FINDER_MIN_MASS", "FINDER_MIN_ELONGATION", "FINDER_MIN_LENGTH_PX",
           "FINDER_RIVAL_SHARE", "FINDER_MAX_TILT_DEG", "FINDER_PICK_RADIUS_PX", "FINDER_PICK_MIN_PEAK", "FINDER_PICK_MIN_MASS", "band_shaped",
           "distance_to_segment", "rope_from_finder", "FINDER_SUPPORT_RADIUS_PX", "FINDER_SUPPORT_MIN_PEAK",
           "finder_support", "finder_check"]

FINDER_MIN_PEAK: float = 6.0
FINDER_MIN_MASS: float = 6.0
FINDER_MIN_ELONGATION: float = 3.0
FINDER_MIN_LENGTH_PX: float = 6.0
FINDER_RIVAL_SHARE: float = 0.5
#: the band runs across a standing stem: at most this far from the photo's horizontal (camera
#: roll, lean and the tilt of stems near the photo's edges stay well within it)
FINDER_MAX_TILT_DEG: float = 45.0
#: at a user's tap (``--pick``): a candidate passing within this many pixels of it, at lower
#: confidence (the tap says where the rope is)
FINDER_PICK_RADIUS_PX: float = 15.0
FINDER_PICK_MIN_PEAK: float = 1.0
FINDER_PICK_MIN_MASS: float = 2.0


def band_shaped(c) -> bool:
    """Is candidate ``c`` a band across a stem (long against its thickness, not a blob; not steeper
    than :data:`FINDER_MAX_TILT_DEG`)?"""
    tilt = np.degrees(np.arctan2(abs(float(c.direction[1])), abs(float(c.direction[0])) + 1e-12))
    return (c.length_px >= FINDER_MIN_ELONGATION * c.thickness_px and c.length_px >= FINDER_MIN_LENGTH_PX
            and tilt <= FINDER_MAX_TILT_DEG)


def distance_to_segment(c, xy) -> float:
    """Photo-pixel distance from ``xy`` to candidate ``c``'s centre line (its two end points)."""
    a, b = np.asarray(c.polyline[0], float), np.asarray(c.polyline[-1], float)
    p = np.asarray(xy, float)
    d = b - a
    t = float(np.clip((p - a) @ d / max(float(d @ d), 1e-9), 0.0, 1.0))
    return float(np.hypot(*(p - a - t * d)))


def rope_from_finder(components, shape: tuple[int, int], *, pick_xy=None, min_peak: float = FINDER_MIN_PEAK,
                     min_mass: float = FINDER_MIN_MASS, rival_share: float = FINDER_RIVAL_SHARE) -> RopeDetection:
    """The rope as :func:`.rope.detect_rope` gives it, from the finder's ``components`` (best first).

    Parameters
    ----------
    components : list of RopeComponent, photo pixels of an image of ``shape`` = (H, W).
    pick_xy : (x, y) a user's tap on the rope: the best candidate within
        :data:`FINDER_PICK_RADIUS_PX` of it above the pick thresholds, no rival rule.
    min_peak, min_mass, rival_share : the acceptance rule (module docstring).

    Returns
    -------
    RopeDetection : found, or not (``ambiguous`` when two candidates qualify), with the reason.
    """
    H, W = shape
    if pick_xy is not None:
        good = [c for c in components if band_shaped(c) and c.peak >= FINDER_PICK_MIN_PEAK
                and c.mass >= FINDER_PICK_MIN_MASS and distance_to_segment(c, pick_xy) <= FINDER_PICK_RADIUS_PX]
        if not good:
            return RopeDetection(False, f"no red rope found at the picked point ({pick_xy[0]:.0f},{pick_xy[1]:.0f})")
        good.sort(key=lambda c: distance_to_segment(c, pick_xy))
        best, rivals = good[0], []
    else:
        good = [c for c in components if band_shaped(c) and c.peak >= min_peak and c.mass >= min_mass]
        if not good:
            return RopeDetection(False, "no red rope found (no thin red band across a trunk)")
        best = good[0]
        rivals = [c for c in components if c is not best and band_shaped(c) and c.peak >= min_peak
                  and c.mass >= rival_share * best.mass]
    if rivals:
        r = rivals[0]
        return RopeDetection(False, f"two rope candidates at ({best.center_xy[0]:.0f},{best.center_xy[1]:.0f}) "
                                    f"and ({r.center_xy[0]:.0f},{r.center_xy[1]:.0f}) (e.g. two roped trees): "
                                    f"--pick X,Y to choose one", ambiguous=True)
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


#: the cross-check of a rope found by the band detector or the stem search: a finder candidate
#: passing within this many pixels (or half its thickness + 4) of the rope's centre supports it
FINDER_SUPPORT_RADIUS_PX: float = 8.0
#: ... at these log-odds or more (p 0.73: any evidence at all). Calibration sets (seeds
#: 9100-9600): the 314 right ropes the pipeline measured had support >= 2.77, the 2 wrong ones
#: (red leaves in a rope-free scene, tape on another tree) none; see ``docs/decisions/rope-finder.md``
FINDER_SUPPORT_MIN_PEAK: float = 1.0


def finder_support(components, xy) -> float:
    """The highest log-odds of the finder candidates passing near ``xy`` (``-inf`` when none).

    Near: within ``max(FINDER_SUPPORT_RADIUS_PX, thickness / 2 + 4)`` photo pixels of the
    candidate's centre line.
    """
    near = [c.peak for c in components
            if distance_to_segment(c, xy) <= max(FINDER_SUPPORT_RADIUS_PX, 0.5 * c.thickness_px + 4.0)]
    return float(max(near)) if near else float("-inf")


def finder_check(rope, components, shape: tuple[int, int], whole=None) -> tuple[str, RopeDetection | None]:
    """The rope finder's verdict on a rope found by the classical detectors.

    The band detector can take a red band that is no rope (tape on another tree, red leaves,
    a jacket's edge) where the real rope is faint to it, and the stem search a red row of bark.
    The finder, trained with such distractors, marks nearly every rope those two find, thin
    ones included (calibration sets: every right rope measured had log-odds >= 2.77 at its
    centre), and is rarely wrong when it is confident. So:

    - ``("supported", None)``: a finder candidate passes through the rope
      (:func:`finder_support` >= :data:`FINDER_SUPPORT_MIN_PEAK`): keep it;
    - ``("replaced", det)``: no support, and the finder accepts a band of its own elsewhere
      (:func:`rope_from_finder`, the shipped rule): that band is the rope;
    - ``("unsupported", None)``: no support and no band of the finder's: the band is no rope
      as far as the photo shows (the user can still tap it: ``--pick`` skips this check).

    Parameters
    ----------
    rope : RopeDetection found by the band detector or the stem search (working-image pixels).
    components : the finder's candidates on the same image (or on one tile around the rope,
        :meth:`~monodbh.models.runtime_ropeseg.RopeFinder.components_near`), best first.
    shape : (H, W) of the image.
    whole : optional callable returning the candidates of the whole image, called only when
        ``components`` do not support the rope (the finder's own band may be anywhere).

    Returns
    -------
    (verdict, RopeDetection or None)

    Examples
    --------
    >>> from monodbh.models.runtime_ropeseg import rope_components
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
    if finder_support(components, rope.center_xy) >= FINDER_SUPPORT_MIN_PEAK:
        return "supported", None
    alt = rope_from_finder(whole() if whole is not None else components, shape)
    if alt:
        return "replaced", alt
    return "unsupported", None
