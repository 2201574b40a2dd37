"""The rope detectors' tuning parameters, one frozen dataclass per detector; imported by the
detector modules of :mod:`monodbh.toolkit.rope` and by callers that pass a different configuration.

Every detector function takes ``config=None``, meaning the default instance of its class. Each
field says what it means and links the decision record that explains how its value was chosen.

Examples
--------
>>> from dataclasses import replace
>>> strict = replace(BandConfig(), min_score=2.0)
>>> strict.min_score, BandConfig().min_score
(2.0, 1.0)
"""
from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["BandConfig", "StemSearchConfig", "FinderConfig", "RopeConfig"]


def _band_weights() -> dict[str, float]:
    return dict(bias=-1.085, log_contrast=1.956, log_length=0.456, log_density=-0.208, coverage=2.745,
                shape=1.359, hue=-13.054, edge_min=1.022, edge_max=1.605, log_clutter=-0.774, members=-0.279,
                coarse=-1.259, resid=-0.589, step=-2.38, corr=1.012, red_area=-2.366, peaky=-0.244,
                log_red=0.419, log_edge_snr=1.163)


def _stem_weights() -> dict[str, float]:
    return {"bias": -8.57, "log_contrast": 0.637, "log_zpix": 1.043, "log_zprof": 0.427, "log_width": 1.274,
            "second": 0.306, "red_shift": 1.023, "h_lo": -1.169, "h_hi": -1.058, "main": 0.44, "orange": 1.11}


@dataclass(frozen=True)
class BandConfig:
    """Parameters of the classical band detector (:func:`monodbh.toolkit.rope.band.detect_rope`).

    Lengths are in pixels of the level they are applied at (the working copy unless noted).
    ``score_weights`` is a plain dict: treat it as read-only (pass a new dict to change it).
    """

    #: log-odds weights of the candidate score, ``bias + sum_k w_k * feature_k``
    #: (docs/decisions/band-detector.md)
    score_weights: dict = field(default_factory=_band_weights)
    #: a candidate scoring above this is a rope (docs/decisions/band-detector.md)
    min_score: float = 1.0
    #: rival bands scoring within this many log-odds of the best make the result ambiguous
    #: (docs/decisions/band-detector.md)
    ambiguity_margin: float = 1.0
    #: of the best and its rivals, a band this many times longer than each other one is taken
    #: (the nearer, larger roped trunk) (docs/decisions/band-detector.md)
    nearer_ratio: float = 1.6
    #: bands are searched on a copy downscaled to this long side, full-resolution pixels
    #: (docs/decisions/work-resolution.md)
    work_long_side_px: int = 1600
    #: pyramid levels searched for thin lines (each halves the copy; a level finds lines up to
    #: about 5 px thick there: 4 levels reach bands about 40 px thick in the working copy, a
    #: 50 mm strap from 1.5 m on a 12 MP photo; docs/decisions/band-detector.md)
    pyramid_levels: int = 4
    #: line-contrast level (red-ness units) of the pixels forming pieces (docs/decisions/band-detector.md)
    piece_threshold: float = 0.012
    #: minimum mean red-ness contrast of a piece or band (docs/decisions/band-detector.md)
    min_contrast: float = 0.015
    #: blur along the line before the thin-line contrast, pixels of each pyramid level
    #: (docs/decisions/band-detector.md)
    sigma_x_px: float = 2.0
    #: at most this many line pieces (the most contrasted) are linked into bands
    #: (docs/decisions/band-detector.md)
    max_segments: int = 400
    #: this many bands (by the cheap band score) get the full score, plus up to half as many
    #: from image squares none of them occupies (docs/decisions/band-detector.md)
    max_candidates: int = 50
    #: log-odds taken off the bands scored beyond ``max_candidates`` (docs/decisions/band-detector.md)
    deep_prior: float = 0.5
    #: bands more orange than this ``(G - B) / R`` are tape, not rope (docs/decisions/band-detector.md)
    max_hue: float = 0.35
    #: band length over thickness below which a band is no rope (docs/decisions/band-detector.md)
    min_elongation: float = 5.0
    #: trunk-edge feature: height of each strip above and below the band, as a fraction of the
    #: band's length (docs/decisions/band-detector.md)
    edge_strip: float = 0.2
    #: trunk-edge feature: number of strips on each side of the band (docs/decisions/band-detector.md)
    edge_strips: int = 2


@dataclass(frozen=True)
class StemSearchConfig:
    """Parameters of the mask-guided stem search and its rope-verifier glue
    (:mod:`monodbh.toolkit.rope.stem_search`).

    ``weights`` is a plain dict: treat it as read-only (pass a new dict to change it).
    """

    #: logistic weights of a stem band's score, ``bias + sum_k w_k * feature_k``
    #: (docs/decisions/stem-search.md)
    weights: dict = field(default_factory=_stem_weights)
    #: a trunk-like stem band scoring above this is the rope (docs/decisions/stem-search.md)
    min_score: float = -1.0
    #: ... or above this one at a user's tap (docs/decisions/stem-search.md)
    pick_min_score: float = -4.0
    #: ... and standing out of the pixel noise by at least this many standard errors at a tap
    #: (docs/decisions/stem-search.md)
    pick_min_zpix: float = 2.0
    #: a band on another stem scoring within this margin of the best makes the result ambiguous
    #: (docs/decisions/stem-search.md)
    ambiguity_margin: float = 1.0
    #: between two band-detector candidates, the other's stem band must score this far below
    #: ``min_score`` for the stem evidence to choose (docs/decisions/stem-search.md)
    evidence_margin: float = 2.0
    #: a band is on a trunk when the instance crosses its row in at most this many pieces
    #: (docs/decisions/stem-search.md)
    max_runs: int = 1
    #: ... and the instance's width 4-6 rows above and below it varies by at most this log ratio
    #: (docs/decisions/stem-search.md)
    max_width_change: float = 0.4
    #: band angles to the image rows that are tried, degrees (docs/decisions/stem-search.md)
    tilts_deg: tuple = tuple(range(-15, 16, 3))
    #: instances with fewer pixels are skipped (docs/decisions/stem-search.md)
    min_pixels: int = 150
    #: a row counts when at least this many instance pixels lie on it (docs/decisions/stem-search.md)
    min_width_px: int = 5
    #: hypotheses (on different rows) each stem contributes (docs/decisions/stem-search.md)
    per_stem: int = 2
    #: ... at a user's tap, at least this many (docs/decisions/stem-search.md)
    pick_per_stem: int = 3
    #: rows this close to the top or bottom of the photo are not bands (docs/decisions/stem-search.md)
    border_px: int = 8
    #: at a tap, only rows within this many pixels of it (docs/decisions/stem-search.md)
    near_px: float = 8.0
    #: at a tap off every stem, the nearest stem within this fraction of the photo's width
    #: (docs/decisions/stem-search.md)
    pick_stem_radius_frac: float = 0.03
    #: bands per stem shown to the rope verifier (as in its training banks)
    #: (docs/decisions/rope-verifier.md)
    verifier_per_stem: int = 4
    #: log-odds the rope verifier needs (docs/decisions/rope-verifier.md)
    verifier_min_logit: float = 3.0
    #: a verified band on another stem within this margin of the best makes the result ambiguous
    #: (docs/decisions/rope-verifier.md)
    verifier_margin: float = 1.0


@dataclass(frozen=True)
class FinderConfig:
    """Acceptance of the mask-free rope finder's candidates (:mod:`monodbh.toolkit.rope.finder`)."""

    #: a candidate is the rope at this peak log-odds or more (docs/decisions/rope-finder.md)
    min_peak: float = 6.0
    #: ... and this summed probability or more (about that many 2 x 2 photo-pixel cells)
    #: (docs/decisions/rope-finder.md)
    min_mass: float = 6.0
    #: band-shaped: at least this many thicknesses long (docs/decisions/rope-finder.md)
    min_elongation: float = 3.0
    #: ... and at least this many photo pixels long (docs/decisions/rope-finder.md)
    min_length_px: float = 6.0
    #: ... and at most this far from the photo's horizontal, degrees (docs/decisions/rope-finder.md)
    max_tilt_deg: float = 45.0
    #: another qualifying candidate with this share of the best one's mass is a rival
    #: (docs/decisions/rope-finder.md)
    rival_share: float = 0.5
    #: at a user's tap: a candidate passing within this many photo pixels of it
    #: (docs/decisions/rope-finder.md)
    pick_radius_px: float = 15.0
    #: ... at this peak log-odds or more (docs/decisions/rope-finder.md)
    pick_min_peak: float = 1.0
    #: ... and this summed probability or more (docs/decisions/rope-finder.md)
    pick_min_mass: float = 2.0
    #: cross-check: a candidate within this many photo pixels (or half its thickness + 4) of a
    #: rope's centre supports it (docs/decisions/rope-finder.md)
    support_radius_px: float = 8.0
    #: ... at this peak log-odds or more (docs/decisions/rope-finder.md)
    support_min_peak: float = 1.0


@dataclass(frozen=True)
class RopeConfig:
    """Parameters of the rope cascade (:func:`~.select.select_rope`) and of the detectors it runs.

    Attributes
    ----------
    weak_score : a band detector candidate scoring between this and the detector's own
        minimum is accepted only across a segmented trunk (docs/decisions/rope-weak-score.md).
    ambiguity_candidates : at most this many competing candidates (within the band detector's
        ``ambiguity_margin`` of the best one) are checked.
    pick_near_px : a tap within ``max(pick_near_px, 2 mask cells)`` of the band detector's band
        is that band (on a near stem the band runs far from its middle).
    pick_end_reach : a tap farther off, but on red running on unbroken into the band (its knot or
        a loose end hanging from it, :func:`~.geometry.red_path_to_band`), is that band too, up
        to this fraction of the working image's long side away (docs/decisions/taps.md).
    finder_cross_check : the rope finder checks the classical detectors' rope
        (docs/decisions/rope-finder.md).
    finder_check_max_marker_mm : the check is skipped when the user's marker is wider than this
        (mm): the rope finder was trained on 5-15 mm ropes and refuses wide straps
        (docs/decisions/rope-finder.md).
    wide_marker_min_elongation : for such a wide marker, the band detector keeps bands at least
        this many times as long as thick (instead of ``band.min_elongation``): a 40 mm strap
        round a 15 cm stem is under 4 times as long as it is wide (docs/decisions/band-detector.md).
    wide_marker_min_px : ... and the finder's check is skipped only for a band at least this thick
        (working-image pixels: a 40 mm strap within about 10 m); a thinner band, or a row found
        through the stem's profile, is checked as a rope is (docs/decisions/rope-finder.md).
    band, stem_search, finder : the detectors' own parameters.
    """
    weak_score: float = 0.0
    ambiguity_candidates: int = 4
    pick_near_px: float = 15.0
    pick_end_reach: float = 0.25
    finder_cross_check: bool = True
    finder_check_max_marker_mm: float = 15.0
    wide_marker_min_elongation: float = 2.5
    wide_marker_min_px: float = 4.0
    band: BandConfig = field(default_factory=BandConfig)
    stem_search: StemSearchConfig = field(default_factory=StemSearchConfig)
    finder: FinderConfig = field(default_factory=FinderConfig)
