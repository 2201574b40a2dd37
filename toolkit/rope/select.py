"""The rope cascade: which detector's rope is measured in a photo, or why none is.

Lives here: :func:`select_rope`, the one place that orders the rope detectors (band detector,
stem search with the rope verifier, the mask-free rope finder) and their checks, and returns a
:class:`RopeChoice`. Imported by :mod:`monodbh.toolkit.pipeline`; imports the rope detectors of this package.

Order (each step runs only where the ones before it leave the photo without a rope):

1. the band detector over the whole photo (no mask needed: it runs while the segmenter does);
   two bands alike are settled by the segmented trunks (:func:`rope_across_trunk`) or by the
   stem search's evidence; a weak band must lie across a segmented trunk;
2. the stem search (a rope thinner than a pixel, as a red row across a segmented trunk), its
   rows scored by the rope verifier network;
3. the rope finder network (no mask), where neither found a rope;
4. the finder checks a rope the first two found: where it sees nothing at that band, its own
   confident band replaces it, or the photo is refused.

At a tap (``pick_xy``) the band detector's band near the tap is kept when rope-like (or when the
tap lies on red that runs on into it: the knot or a loose end hanging from it), else the stem
search and then the finder look at the tap; a band the finder marks through the tap replaces the
stem search's row there; the finder check is skipped.
"""
from __future__ import annotations

import enum
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from .band import detect_rope
from .config import RopeConfig
from .finder import finder_check, finder_support, rope_from_finder
from .geometry import distance_to_band, instance_in_window, red_path_to_band
from .stem_search import detect_rope_on_stems, stem_evidence_choice

__all__ = ["RopeSource", "Refusal", "RopeChoice", "select_rope", "rope_across_trunk"]


class RopeSource(enum.Enum):
    """Which detector gave the measured rope."""
    #: the classical band detector (the rope seen as a line; its thickness can be a ruler)
    BAND = "band"
    #: the stem search: a red row across a segmented trunk
    STEM_PROFILE = "stem_profile"
    #: the stem search's row chosen by the rope verifier network
    STEM_VERIFIED = "stem_verified"
    #: the rope finder network, where the others found none (or at a tap)
    FINDER = "finder"
    #: the rope finder's band, replacing a band the classical detectors took that it does not see
    FINDER_OVER_CLASSICAL = "finder_over_classical"

    @property
    def flags(self) -> list[str]:
        """The result flags that tell the user which detector found the rope."""
        return list(_SOURCE_FLAGS[self])

    @property
    def is_line(self) -> bool:
        """Whether the rope was seen as a line by the band detector (its thickness is measured)."""
        return self is RopeSource.BAND

    @property
    def spans_stem(self) -> bool:
        """Whether the rope's extent is its own extent across the stem (checks the stem's width):
        the band detector's and the finder's bands, not the stem search's row."""
        return self not in (RopeSource.STEM_PROFILE, RopeSource.STEM_VERIFIED)


_SOURCE_FLAGS = {
    RopeSource.BAND: (),
    RopeSource.STEM_PROFILE: ("rope_from_stem_profile",),
    RopeSource.STEM_VERIFIED: ("rope_from_stem_profile", "rope_verified_by_network"),
    RopeSource.FINDER: ("rope_found_by_network",),
    RopeSource.FINDER_OVER_CLASSICAL: ("rope_found_by_network", "rope_chosen_by_network"),
}


class Refusal(enum.Enum):
    """Why no rope is measured."""
    #: no detector found a rope (or two alike): the detector's own reason
    NOT_FOUND = "not_found"
    #: nothing rope-like at the tapped point
    PICK_MISSED = "pick_missed"
    #: a faint band that lies across no segmented trunk
    WEAK_OFF_TRUNK = "weak_off_trunk"
    #: a band the rope finder does not see as a rope
    FINDER_UNSUPPORTED = "finder_unsupported"


@dataclass
class RopeChoice:
    """What :func:`select_rope` decided; truthy when a rope is to be measured.

    Attributes
    ----------
    rope : the rope (:class:`~.rope.RopeDetection`, working-image pixels), or the last
        detection tried (its ``reason`` says why it is no rope) when refused.
    source : which detector gave it (None when refused).
    refusal : why none is measured (None when a rope was chosen).
    at_xy : (2,) working-image pixel the refusal is about (the refused band), or None.
    timings_ms : ``segment`` (the wait for the segmenter), ``rope_finder`` where it ran.
    tap_on_rope_end : the tap lay off the band, on red running on into it (a knot or loose end).
    """
    rope: object
    source: RopeSource | None = None
    refusal: Refusal | None = None
    at_xy: np.ndarray | None = None
    timings_ms: dict = field(default_factory=dict)
    tap_on_rope_end: bool = False

    def __bool__(self) -> bool:
        return self.refusal is None

    @property
    def flags(self) -> list[str]:
        """The result flags of the chosen rope's detector (and ``pick_on_rope_end``)."""
        out = self.source.flags if self.source is not None else []
        return out + ["pick_on_rope_end"] if self.tap_on_rope_end else out


def rope_across_trunk(rope, instance: np.ndarray, cell: float) -> bool:
    """Whether a rope band lies across a segmented tree instance and spans about its width.

    Parameters
    ----------
    rope : :class:`~.rope.RopeDetection` or candidate (``center_xy``, ``direction``, ``polyline``).
    instance : (H, W) int tree instance ids (0 = none), same pixels as the rope.
    cell : size of one segmenter mask cell in pixels (the masks' resolution).
    """
    tid = instance_in_window(instance, rope.center_xy, max(6, int(round(cell))))
    if tid == 0:
        return False
    on, k0 = _instance_along_band(rope, instance, tid)
    if not on[max(0, k0 - int(cell)):k0 + int(cell) + 1].any():
        return False
    width = _run_width(on, k0, cell)
    pl = np.asarray(rope.polyline, np.float64)
    length = float(np.hypot(*np.diff(pl, axis=0).T).sum()) if len(pl) > 1 else 0.0
    return 0.4 * width <= length <= 2.0 * width + 2 * cell


def _instance_along_band(rope, instance, tid):
    """(samples along the band's line, 1 px apart, that are on instance ``tid``; the index of the
    rope's centre)."""
    H, W = instance.shape
    c = np.asarray(rope.center_xy, np.float64)
    u = np.asarray(rope.direction, np.float64)
    u = u / max(np.linalg.norm(u), 1e-9)
    t = np.arange(-0.6 * W, 0.6 * W, 1.0)
    pts = c[None] + t[:, None] * u[None]
    xi, yi = np.round(pts[:, 0]).astype(int), np.round(pts[:, 1]).astype(int)
    ok = (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
    on = np.zeros(len(t), bool)
    on[ok] = instance[yi[ok], xi[ok]] == tid
    return on, int(np.argmin(np.abs(t)))


def _run_width(on, k0, cell) -> float:
    """Length of the run of ``on`` samples nearest ``k0`` (gaps under one mask cell bridged)."""
    idx = np.nonzero(on)[0]
    k = idx[np.argmin(np.abs(idx - k0))]
    lo = hi = k
    while lo > 0 and on[max(0, lo - int(cell) - 1):lo].any():
        lo -= 1
    while hi < len(on) - 1 and on[hi + 1:hi + int(cell) + 2].any():
        hi += 1
    return float(hi - lo + 1)


class _FinderView:
    """The rope finder network's candidates for one photo, each computed at most once: the whole
    image's, and one tile's around a point."""

    def __init__(self, finder, img, timings: dict):
        self._finder, self._img, self._tm = finder, img, timings
        self._whole = None
        self._near = {}

    def _timed(self, fn, *args):
        t = time.perf_counter()
        try:
            return fn(*args)
        finally:
            self._tm["rope_finder"] = self._tm.get("rope_finder", 0.0) + 1000 * (time.perf_counter() - t)

    def whole(self):
        if self._whole is None:
            self._whole = self._timed(self._finder.components, self._img)
        return self._whole

    def near(self, xy):
        key = (float(xy[0]), float(xy[1]))
        if key not in self._near:
            self._near[key] = self._timed(self._finder.components_near, self._img, xy)
        return self._near[key]


@dataclass
class _State:
    """The cascade's working state for one photo (internal)."""
    rope: object
    source: RopeSource | None = None
    weak_refused: bool = False
    pick_missed: bool = False
    tap_on_rope_end: bool = False


def select_rope(img: np.ndarray, segment: Callable[[], np.ndarray], cell: float, *, pick_xy=None,
                verifier=None, finder=None, config: RopeConfig | None = None,
                marker_width_mm: float | None = None) -> RopeChoice:
    """Find the rope to measure in the working image.

    Parameters
    ----------
    img : (h, w, 3) uint8 working image.
    segment : returns the segmenter's (h, w) tree instance ids; called once, after the band
        detector (the segmenter runs beside it on another thread); its wait is ``segment``.
    cell : one segmenter mask cell in pixels.
    pick_xy : (x, y) tapped working-image pixel (``--pick``), or None.
    verifier : the rope verifier network (:class:`~monodbh.models.runtime.rope_verifier.RopeVerifier`) or None.
    finder : the rope finder network (:class:`~monodbh.models.runtime.rope_finder.RopeFinder`) or None.
    config : :class:`RopeConfig` (defaults when None).
    marker_width_mm : the user's marker width (``--rope-mm`` / the camera file), or None; wider
        than :attr:`RopeConfig.finder_check_max_marker_mm`, the finder does not check the band.

    Returns
    -------
    :class:`RopeChoice`.
    """
    cfg = config or RopeConfig()
    tm: dict = {}
    wide = marker_width_mm is not None and marker_width_mm > cfg.finder_check_max_marker_mm
    if wide:
        cfg = replace(cfg, band=replace(cfg.band, min_elongation=min(cfg.band.min_elongation,
                                                                     cfg.wide_marker_min_elongation)))
    st = _State(detect_rope(img, None, pick_xy=pick_xy, weak_score=cfg.weak_score, config=cfg.band), RopeSource.BAND)
    t_seg = time.perf_counter()
    instance = segment()
    tm["segment"] = 1000 * (time.perf_counter() - t_seg)
    if not st.rope and st.rope.ambiguous and pick_xy is None:
        st.rope = _settle_ambiguity(img, st.rope, instance, cell, cfg)
    st.weak_refused = bool(st.rope) and st.rope.weak and not rope_across_trunk(st.rope, instance, cell)
    off_pick = (pick_xy is not None and bool(st.rope)
                and distance_to_band(st.rope, pick_xy) > max(cfg.pick_near_px, 2 * cell))
    if off_pick and red_path_to_band(img, st.rope, pick_xy, reach_px=cfg.pick_end_reach * max(img.shape[:2])):
        # the tap is on the knot or a loose end hanging from the band: the band is what was meant
        pick_xy, off_pick, st.tap_on_rope_end = tuple(np.asarray(st.rope.center_xy, float)), False, True
    _stem_search(img, instance, st, pick_xy, off_pick, verifier, cfg)
    # the finder knows ropes, not wide straps: a band as thick as a strap seen from a measuring
    # distance is not checked by it but must lie across a segmented trunk; a thin band, or a row
    # found through the stem's profile, is checked as a rope is
    strap_like = (wide and bool(st.rope) and st.source is RopeSource.BAND and not st.weak_refused
                  and float(st.rope.thickness_px or 0.0) >= cfg.wide_marker_min_px)
    if strap_like and pick_xy is None and not rope_across_trunk(st.rope, instance, cell):
        st.weak_refused, strap_like = True, False
    if finder is not None:
        _finder_stage(_FinderView(finder, img, tm), img.shape[:2], st, pick_xy, cfg, check=not strap_like)
    return _choice(st, pick_xy, tm)


def _settle_ambiguity(img, rope, instance, cell, cfg):
    """Two bands score alike: when exactly one of the leading ones lies across a segmented trunk,
    that one is the rope (the other is e.g. red paint, tape or clothing); else when exactly one sits
    on a stem with a rope-like red row there. Otherwise the ambiguous detection stays."""
    top = [c for c in rope.candidates
           if c.score >= rope.candidates[0].score - cfg.band.ambiguity_margin][:cfg.ambiguity_candidates]
    on = [c for c in top if rope_across_trunk(c, instance, cell)]
    if len(on) == 1:
        return detect_rope(img, None, pick_xy=on[0].center_xy, config=cfg.band)
    k = stem_evidence_choice(img, instance, [c.center_xy for c in top], rope_candidates=rope.candidates,
                             config=cfg.stem_search)
    if k is not None:
        return detect_rope(img, None, pick_xy=top[k].center_xy, config=cfg.band)
    return rope


def _stem_search(img, instance, st: _State, pick_xy, off_pick: bool, verifier, cfg) -> None:
    """The stem search where the band detector found no rope, only a weak band off every trunk, or
    (at a tap) nothing rope-like near the tap."""
    rope = st.rope
    if not ((not rope and not rope.ambiguous) or st.weak_refused
            or (pick_xy is not None and (not rope or off_pick or rope.score < cfg.weak_score))):
        return
    alt = detect_rope_on_stems(img, instance, pick_xy=pick_xy, rope_candidates=rope.candidates,
                               verifier=verifier, config=cfg.stem_search)
    if alt:
        st.rope, st.weak_refused = alt, False
        st.source = (RopeSource.STEM_VERIFIED if verifier is not None and pick_xy is None
                     else RopeSource.STEM_PROFILE)
    elif off_pick:
        st.pick_missed = True       # the nearest band is elsewhere: not what the user tapped


def _finder_stage(view: _FinderView, shape, st: _State, pick_xy, cfg, check: bool = True) -> None:
    """The rope finder: where no rope was found (or a tap found none), else as a check (unless
    ``check`` is off)."""
    rope = st.rope
    no_rope = not rope and not rope.ambiguous
    if st.pick_missed or no_rope or (pick_xy is None and st.weak_refused):
        _finder_alone(view, shape, st, pick_xy, cfg)
    elif not (cfg.finder_cross_check and check):
        return
    elif pick_xy is None and rope and not st.weak_refused:
        _finder_check(view, shape, st, cfg)
    elif pick_xy is not None and rope and st.source in (RopeSource.BAND, RopeSource.STEM_PROFILE):
        _finder_at_tap(view, shape, st, pick_xy, cfg)


def _finder_alone(view, shape, st: _State, pick_xy, cfg) -> None:
    """The mask-free finder over the whole photo (the segmenter may have missed or split the
    roped stem); at a tap, its candidate there."""
    alt = rope_from_finder(view.whole(), shape, pick_xy=pick_xy, config=cfg.finder)
    if alt or (alt.ambiguous and pick_xy is None):
        st.rope, st.weak_refused, st.pick_missed = alt, False, False
        st.source = RopeSource.FINDER if alt else None


def _finder_check(view, shape, st: _State, cfg) -> None:
    """The finder checks the classical detectors' rope (tape or leaves taken where the real rope
    was faint to them): one tile around the band tells support, the whole photo only without it."""
    verdict, alt = finder_check(st.rope, view.near(st.rope.center_xy), shape, whole=view.whole, config=cfg.finder)
    if verdict == "replaced":
        st.rope, st.source = alt, RopeSource.FINDER_OVER_CLASSICAL
    elif verdict == "unsupported":
        st.source = None


def _finder_at_tap(view, shape, st: _State, pick_xy, cfg) -> None:
    """At a tap the finder's band through the tap replaces the band detector's band where that
    lies off the tap (up to two mask cells: a band beside the rope's end) and the finder marks none
    at it, and the stem search's row wherever the finder marks one: the row spans whatever instance
    lies under the tap (a trunk merged with its neighbours, a crown), the band the rope's own
    extent (docs/decisions/taps.md)."""
    band = st.source is RopeSource.BAND
    if band and distance_to_band(st.rope, pick_xy) <= cfg.finder.pick_radius_px:
        return
    comps = view.near(pick_xy)
    if band and finder_support(comps, st.rope.center_xy, config=cfg.finder) >= cfg.finder.support_min_peak:
        return
    alt = rope_from_finder(comps, shape, pick_xy=pick_xy, config=cfg.finder)
    if alt:
        st.rope, st.source = alt, RopeSource.FINDER


def _choice(st: _State, pick_xy, tm: dict) -> RopeChoice:
    """The state after the cascade as a :class:`RopeChoice` (refusals in the order they are told)."""
    rope = st.rope
    if st.pick_missed:
        return RopeChoice(rope, refusal=Refusal.PICK_MISSED,
                          at_xy=None if pick_xy is None else np.asarray(pick_xy, np.float64), timings_ms=tm)
    if st.weak_refused:
        return RopeChoice(rope, refusal=Refusal.WEAK_OFF_TRUNK, at_xy=np.asarray(rope.center_xy, np.float64),
                          timings_ms=tm)
    if rope and st.source is None:
        return RopeChoice(rope, refusal=Refusal.FINDER_UNSUPPORTED, at_xy=np.asarray(rope.center_xy, np.float64),
                          timings_ms=tm)
    if not rope:
        return RopeChoice(rope, refusal=Refusal.NOT_FOUND, timings_ms=tm)
    return RopeChoice(rope, source=st.source, timings_ms=tm, tap_on_rope_end=st.tap_on_rope_end)
