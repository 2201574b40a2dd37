"""The rope as a ruler: its thickness across the band, read where the photo has the most pixels.

Lives here: :func:`rope_ruler` (the thickness and contrast the geometry's ``rope_diameter`` scale
source needs), :func:`rope_at_full_resolution` and :func:`wide_marker_width` (a strap wider
than the band detector reads). Imported by :mod:`monodbh.toolkit.pipeline`;
imports the band detector, the rope profile and the marker's edge reader (:mod:`.marker_edges`)
of this package (a :class:`~monodbh.toolkit.frames.WorkFrame` is passed in).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

__all__ = ["RopeRuler", "rope_ruler", "rope_at_full_resolution", "wide_marker_width"]


@dataclass
class RopeRuler:
    """The rope's measured thickness, for the ``rope_diameter`` scale source.

    Attributes
    ----------
    thickness_px : thickness across the band in working-image pixels (None: the rope was not seen
        as a line, e.g. found by the stem search, so it is no ruler).
    thickness_native_px : the same in the pixels it was measured in (the full-resolution photo's
        where it was read there).
    contrast : red-ness contrast of the rope's mean profile across the band (None unless the rope's
        diameter is known).
    edges : the thickness is the marker's silhouette edge to edge
        (:func:`~.marker_edges.marker_thickness`); else the red-ness profile's half-maximum width
        (the geometry corrects it by ``RopeRulerConfig.fwhm_ratio``).
    flags : ``rope_read_at_full_resolution`` where it was read there, ``marker_read_by_edges``.
    """
    thickness_px: float | None = None
    thickness_native_px: float | None = None
    contrast: float | None = None
    edges: bool = False
    flags: list[str] = field(default_factory=list)


def rope_ruler(rgb: np.ndarray, camera, frame, rope, *, is_line: bool, diameter_known: bool,
               full_resolution: bool = True, edges: bool = True, finder_band: bool = False,
               timings: dict | None = None) -> RopeRuler:
    """Read the rope's thickness (and, with a known diameter, how clearly it stands out).

    Parameters
    ----------
    rgb : (H, W, 3) uint8 photo; camera : its :class:`~monodbh.calib.Camera`.
    frame : :class:`~monodbh.toolkit.frames.WorkFrame` of the photo.
    rope : :class:`~.rope.RopeDetection` in working-image pixels.
    is_line : the band detector saw the rope as a line (else it is no ruler, unless ``finder_band``).
    finder_band : the rope finder's band (no thickness of its own, e.g. a strap wider than the
        band detector sees): with a known width and ``edges``, it is read as a wide marker
        (:func:`wide_marker_width`: edge to edge, else its mean profile's half-maximum width);
        where neither holds, it is no ruler.
    diameter_known : the user gave the rope's diameter (``--rope-mm``).
    full_resolution : read it again on the full-resolution photo where that is larger.
    edges : read the thickness edge to edge (:func:`~.marker_edges.marker_thickness`) where it
        fits, else (or off) the red-ness profile's half-maximum width.
    timings : ``rope_ruler`` (ms) is added here when it runs.

    Returns
    -------
    :class:`RopeRuler`.
    """
    if not is_line:
        if finder_band and diameter_known and edges:
            return _finder_ruler(rgb, camera, frame, rope, full_resolution, timings)
        return RopeRuler()
    T = float(rope.thickness_px)
    if not diameter_known:
        return RopeRuler(T, T)
    full = None
    t = time.perf_counter()
    if full_resolution:
        full = rope_at_full_resolution(rgb, camera, frame, rope, edges=edges)
    if full is not None:
        out = RopeRuler(full["thickness_px"] * full["scale"], full["thickness_px"], full["contrast"],
                        full["edges"], ["rope_read_at_full_resolution"])
    else:
        from .profile import rope_profile_fwhm
        fwhm, contrast = rope_profile_fwhm(frame.image, rope.polyline, rope.thickness_px)
        m = _refined_width(frame.image, rope.polyline, T, fwhm_px=fwhm) if edges else None
        out = RopeRuler(T, T, contrast) if m is None else RopeRuler(m[0], m[0], contrast, m[1])
    if out.edges:
        out.flags.append("marker_read_by_edges")
    if timings is not None:
        timings["rope_ruler"] = 1000 * (time.perf_counter() - t)
    return out


#: an edge-to-edge thickness is used when its 1-sigma is under this fraction of it
EDGE_MAX_REL_SIGMA = 0.1
#: ... and when it is this many times the band detector's half-maximum thickness (0.8-1.25 times
#: the tube's diameter that thickness implies, ``RopeRulerConfig.fwhm_ratio`` 0.944): outside, the
#: fit took in the rope's shadow, a tail or the knot (decision record rope-ruler.md)
EDGE_VS_DETECTOR = (0.85, 1.32)


#: a strap the detector read as a stripe of it: its edge-to-edge width is kept where it is this many
#: times the half-maximum width of its mean profile (decision record rope-ruler.md)
EDGE_VS_WIDE_FWHM = (0.85, 1.15)


def wide_marker_width(img: np.ndarray, polyline, thickness_px: float, *, iterations: int = 3,
                      fwhm_fallback: bool = False) -> tuple[float, bool] | None:
    """A wide marker's thickness from a rough one.

    The half-maximum width of the band's mean red-ness profile (:func:`~.profile.rope_profile_fwhm`)
    is read again in a window sized by itself while it grows by :data:`EDGE_VS_DETECTOR`'s upper
    end or more (at most ``iterations`` times); the edges (:func:`~.marker_edges.marker_thickness`)
    are then read in a window sized by it and kept where they are determined to
    :data:`EDGE_MAX_REL_SIGMA` and agree with it within :data:`EDGE_VS_WIDE_FWHM`. With
    ``fwhm_fallback``, where they are not, the half-maximum width itself is returned.

    Parameters
    ----------
    img : (H, W, 3) uint8 image; polyline : (N, 2) the band's centre line in its pixels.
    thickness_px : rough thickness (pixels).

    Returns
    -------
    ``(thickness px, edges)`` (``edges``: read edge to edge, else the half-maximum width), or None.
    """
    from .marker_edges import marker_thickness
    from .profile import rope_profile_fwhm

    P = np.asarray(polyline, np.float64)
    T = max(float(thickness_px), 1.0)
    fwhm = rope_profile_fwhm(img, P, T)[0]
    for _ in range(iterations):
        if not (np.isfinite(fwhm) and fwhm >= EDGE_VS_DETECTOR[1] * T):
            break
        T = fwhm
        fwhm = rope_profile_fwhm(img, P, T)[0]
    if not (np.isfinite(fwhm) and fwhm > 1.0):
        return None
    m = marker_thickness(img, P, fwhm)
    lo, hi = EDGE_VS_WIDE_FWHM
    if m is not None and m.sigma_px < EDGE_MAX_REL_SIGMA * m.width_px and lo < m.width_px / fwhm < hi:
        return float(m.width_px), True
    return (float(fwhm), False) if fwhm_fallback else None


def _refined_width(img: np.ndarray, polyline, thickness_px: float,
                   fwhm_px: float | None = None) -> tuple[float, bool] | None:
    """``(thickness px, edges)``: the marker's edge-to-edge thickness
    (:func:`~.marker_edges.marker_thickness`, ``edges`` True) where it is determined to
    :data:`EDGE_MAX_REL_SIGMA` and agrees with the detector's ``thickness_px`` within
    :data:`EDGE_VS_DETECTOR`; else None (the detector's thickness stands).

    The band detector can read a wide strap, or a thick round rope whose shaded half is no longer
    "red", as a stripe of it. Where the half-maximum width of the band's mean profile is beyond
    that agreement, the edges are read again in a window sized by it and kept where they agree
    with it within :data:`EDGE_VS_WIDE_FWHM`, else that half-maximum width is the thickness
    (``edges`` False). ``fwhm_px``: that half-maximum width where the caller has read it already
    (read here otherwise)."""
    from .marker_edges import marker_thickness
    from .profile import rope_profile_fwhm

    T = max(float(thickness_px), 1.0)
    P = np.asarray(polyline, np.float64)
    lo, hi = EDGE_VS_DETECTOR
    m = marker_thickness(img, P, T)
    if m is not None and m.sigma_px < EDGE_MAX_REL_SIGMA * m.width_px and lo < m.width_px / T < hi:
        return float(m.width_px), True
    fwhm = rope_profile_fwhm(img, P, T)[0] if fwhm_px is None else float(fwhm_px)
    if not (np.isfinite(fwhm) and fwhm / T >= hi):
        return None
    return wide_marker_width(img, P, fwhm, iterations=0, fwhm_fallback=True)


def _full_res_band(rgb: np.ndarray, camera, frame, rope):
    """``(crop (h, w, 3), polyline in it (N, 2), thickness px, box (x0, y0, x1, y1))``: the band
    of ``rope`` (working-image pixels) on the undistorted full-resolution photo, with rows above
    and below and part of the background beside it; None when the photo is no larger than the
    working image."""
    sx, sy = frame.scale
    if max(sx, sy) > 0.95 or not rope or rope.polyline is None or len(rope.polyline) < 2:
        return None
    P = (np.asarray(rope.polyline, np.float64) + 0.5) / (sx, sy) - 0.5
    T = float(rope.thickness_px) / sx
    L = float(np.linalg.norm(P[-1] - P[0]))
    mx, my = 0.35 * L + 4 * T + 8, max(10 * T, 0.25 * L, 24.0)
    box = tuple(int(round(v)) for v in (P[:, 0].min() - mx, P[:, 1].min() - my,
                                        P[:, 0].max() + mx, P[:, 1].max() + my))
    crop = frame.full_res_crop(rgb, camera, box)
    return crop, P - (box[0], box[1]), T, box


def _finder_ruler(rgb: np.ndarray, camera, frame, rope, full_resolution: bool, timings: dict | None) -> RopeRuler:
    """The rope finder's band read as a wide marker (:func:`wide_marker_width`, its half-maximum
    width where the edges do not hold), on the full-resolution photo where it is larger; an empty
    :class:`RopeRuler` where neither holds."""
    from .profile import rope_profile_fwhm

    t = time.perf_counter()
    out = RopeRuler()
    full = _full_res_band(rgb, camera, frame, rope) if full_resolution else None
    if full is not None:
        img, P, T, _ = full
        scale, flags = float(frame.scale[0]), ["rope_read_at_full_resolution"]
    elif rope and rope.polyline is not None and len(rope.polyline) >= 2:
        img, P, T = frame.image, np.asarray(rope.polyline, np.float64), float(rope.thickness_px)
        scale, flags = 1.0, []
    else:
        return out
    wide = wide_marker_width(img, P, T, fwhm_fallback=True)
    if wide is not None:
        w, by_edges = wide
        out = RopeRuler(w * scale, w, float(rope_profile_fwhm(img, P, w)[1]), by_edges,
                        flags + (["marker_read_by_edges"] if by_edges else []))
    if timings is not None:
        timings["rope_ruler"] = 1000 * (time.perf_counter() - t)
    return out


def _on_band(polyline, P: np.ndarray, T: float) -> bool:
    """Whether a band found at full resolution (centre line ``polyline`` (M, 2)) is a piece of
    the working image's band (centre line ``P`` (N, 2), thickness ``T``, the same pixels): a rope
    interrupted by a twig or the stem's shade is found there in pieces, each as thick as the rope.
    Its points within the band's columns lie within ``max(T, 3)`` px of its centre line (median)."""
    q = np.asarray(polyline, np.float64)
    order = np.argsort(P[:, 0])
    px, py = P[order, 0], P[order, 1]
    inside = (q[:, 0] >= px[0]) & (q[:, 0] <= px[-1])
    if inside.sum() < 2:
        return False
    return float(np.median(np.abs(q[inside, 1] - np.interp(q[inside, 0], px, py)))) <= max(T, 3.0)


def rope_at_full_resolution(rgb: np.ndarray, camera, frame, rope, *, edges: bool = True) -> dict | None:
    """The rope's thickness read again on the full-resolution photo (a 12 MP photo is measured
    at the working long side, where a rope is 2.5x thinner than the sensor sees it).

    The rope band found in the working image is cut out of the undistorted full-resolution
    photo (with rows above and below it and part of the background beside it), the band
    detector is run again there at the same place, and its thickness and mean-profile contrast
    are returned in full-resolution pixels.

    Parameters
    ----------
    rgb : (H, W, 3) uint8 photo; camera : its camera.
    frame : :class:`~monodbh.toolkit.frames.WorkFrame` of the photo.
    rope : :class:`~.rope.RopeDetection` in working-image pixels.
    edges : read the thickness edge to edge where it fits (see :func:`rope_ruler`).

    Returns
    -------
    ``{"thickness_px", "contrast", "scale", "edges"}`` with ``scale`` the working / full-resolution
    pixel ratio and ``edges`` whether the thickness was read edge to edge; None when the photo is
    no larger than the working image or the band is not found again at the same place.
    """
    from .band import detect_rope
    from .profile import rope_profile_fwhm

    full = _full_res_band(rgb, camera, frame, rope)
    if full is None:
        return None
    crop, P, T, box = full
    sx, sy = frame.scale
    L = float(np.linalg.norm(P[-1] - P[0]))
    c = (np.asarray(rope.center_xy, np.float64) + 0.5) / (sx, sy) - 0.5 - (box[0], box[1])
    det = detect_rope(crop, None, pick_xy=(float(c[0]), float(c[1])), min_score=-np.inf)
    if not det or not (np.hypot(*(np.asarray(det.center_xy) - c)) <= max(3 * T, 0.15 * L) + 4
                       or _on_band(det.polyline, P, T)):
        return None
    if not 0.4 < det.thickness_px / max(T, 1e-6) < 2.5:
        return None
    fwhm, contrast = rope_profile_fwhm(crop, det.polyline, det.thickness_px)
    m = _refined_width(crop, det.polyline, det.thickness_px, fwhm_px=fwhm) if edges else None
    return {"thickness_px": float(det.thickness_px if m is None else m[0]), "contrast": float(contrast),
            "scale": float(sx), "edges": m is not None and m[1]}
