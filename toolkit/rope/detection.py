"""What the rope detectors return: a scored rope hypothesis (:class:`RopeCandidate`) and the
detection (:class:`RopeDetection`); imported by every module of :mod:`monodbh.toolkit.rope` and
by its callers.

Both are frozen: the detectors assemble each one once, with all its values.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["RopeCandidate", "RopeDetection", "NO_ROPE"]

#: the error of a photo where no rope was found, with what to do about it: a rope under about
#: 2 px thick in the working image is rarely found (README, "Taking the photo")
NO_ROPE = ("no red rope found (no thin red band across a trunk; retake closer or with a thicker marker "
           "so that it is at least 2 px thick, or give --pick X,Y on it)")


@dataclass(frozen=True)
class RopeCandidate:
    """One scored rope hypothesis (full-resolution pixel coordinates once returned).

    Attributes
    ----------
    center_xy : (x, y) middle of the band.
    direction : unit (dx, dy) of the band at its middle, dx >= 0.
    length_px, thickness_px : band extent along and across.
    score : higher is more rope-like (comparable between candidates of one photo).
    contrast : mean red-ness contrast of the band.
    coverage : fraction of the band's length where it is seen (gaps = occluders).
    span : fraction of the trunk width the band spans (NaN without a tree mask).
    hue : mean orange-ness ``(G - B) / R`` of the band.
    polyline : (N, 2) float32 centre line (x, y).
    features : the values entering the score (see
        :func:`monodbh.toolkit.rope.band_features.candidate_features`).

    The remaining fields are the band detector's own (working-image values): ``level`` (pyramid
    level), ``resid`` (centre-line fit residual), ``members`` (linked pieces), ``red`` (mean
    red-ness), ``deep`` (scored beyond the band-score budget) and the context around the band
    (``clutter``, ``density``, ``edges``, ``edge_snr``, ``step``, ``corr``, ``red_area``,
    ``peaky``; see :class:`monodbh.toolkit.rope.band_features.BandContext`).
    """
    center_xy: tuple[float, float]
    direction: tuple[float, float]
    length_px: float
    thickness_px: float
    score: float = 0.0
    contrast: float = 0.0
    coverage: float = 1.0
    span: float = float("nan")
    hue: float = 0.0
    polyline: np.ndarray | None = field(default=None, repr=False)
    features: dict = field(default_factory=dict, repr=False)
    level: int = field(default=0, repr=False)
    resid: float = field(default=0.0, repr=False)
    members: int = field(default=1, repr=False)
    clutter: float = field(default=0.0, repr=False)
    density: float = field(default=0.0, repr=False)
    edges: tuple = field(default=(0.0, 0.0), repr=False)
    step: float = field(default=0.0, repr=False)
    red: float = field(default=0.0, repr=False)
    red_area: float = field(default=0.0, repr=False)
    peaky: float = field(default=0.0, repr=False)
    edge_snr: float = field(default=0.0, repr=False)
    corr: float = field(default=0.0, repr=False)
    deep: bool = field(default=False, repr=False)

    def as_dict(self) -> dict:
        """JSON-friendly summary."""
        return dict(center_xy=[round(float(v), 1) for v in self.center_xy],
                    direction=[round(float(v), 4) for v in self.direction],
                    length_px=round(float(self.length_px), 1), thickness_px=round(float(self.thickness_px), 2),
                    score=round(float(self.score), 4))


@dataclass(frozen=True)
class RopeDetection:
    """Result of a rope detector; falsy when no (unambiguous) rope was found.

    Attributes
    ----------
    found : a single rope was found.
    reason : why not found, or the ambiguity message naming the candidate positions; ``""`` if found.
    center_xy : (x, y) where the rope crosses the middle of the trunk, full-resolution pixels.
    direction : unit (dx, dy) of the band across the trunk (dx >= 0).
    polyline : (N, 2) float32 rope centre line (x, y) pixels.
    thickness_px : rope thickness across the band, pixels.
    mask : (H, W) bool rope pixels (None when not found).
    score : score of the chosen candidate (0 when none).
    candidates : scored alternatives, best first (for ``--pick`` and error messages).
    ambiguous : two candidates scored within the ambiguity margin (then ``found`` is False).
    weak : found only below ``min_score`` (above ``weak_score``): to be confirmed by the caller.
    timings_ms : time per stage.
    """
    found: bool
    reason: str = ""
    center_xy: tuple[float, float] | None = None
    direction: tuple[float, float] | None = None
    polyline: np.ndarray | None = field(default=None, repr=False)
    thickness_px: float = float("nan")
    mask: np.ndarray | None = field(default=None, repr=False)
    score: float = 0.0
    candidates: list[RopeCandidate] = field(default_factory=list, repr=False)
    ambiguous: bool = False
    timings_ms: dict = field(default_factory=dict, repr=False)
    weak: bool = False

    def __bool__(self) -> bool:
        return bool(self.found)
