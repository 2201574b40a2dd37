"""The rope as a ruler: its thickness across the band, read where the photo has the most pixels.

Lives here: :func:`rope_ruler` (the thickness and contrast the geometry's ``rope_diameter`` scale
source needs) and :func:`rope_at_full_resolution`. Imported by :mod:`monodbh.toolkit.pipeline`;
imports the band detector and the rope profile of this package (a
:class:`~monodbh.toolkit.frames.WorkFrame` is passed in).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

__all__ = ["RopeRuler", "rope_ruler", "rope_at_full_resolution"]


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
    flags : ``rope_read_at_full_resolution`` where it was read there.
    """
    thickness_px: float | None = None
    thickness_native_px: float | None = None
    contrast: float | None = None
    flags: list[str] = field(default_factory=list)


def rope_ruler(rgb: np.ndarray, camera, frame, rope, *, is_line: bool, diameter_known: bool,
               full_resolution: bool = True, timings: dict | None = None) -> RopeRuler:
    """Read the rope's thickness (and, with a known diameter, how clearly it stands out).

    Parameters
    ----------
    rgb : (H, W, 3) uint8 photo; camera : its :class:`~monodbh.calib.Camera`.
    frame : :class:`~monodbh.toolkit.frames.WorkFrame` of the photo.
    rope : :class:`~.rope.RopeDetection` in working-image pixels.
    is_line : the band detector saw the rope as a line (else it is no ruler).
    diameter_known : the user gave the rope's diameter (``--rope-mm``).
    full_resolution : read it again on the full-resolution photo where that is larger.
    timings : ``rope_full_res`` (ms) is added here when it runs.

    Returns
    -------
    :class:`RopeRuler`.
    """
    if not is_line:
        return RopeRuler()
    T = float(rope.thickness_px)
    if not diameter_known:
        return RopeRuler(T, T)
    full = None
    if full_resolution:
        t = time.perf_counter()
        full = rope_at_full_resolution(rgb, camera, frame, rope)
        if timings is not None:
            timings["rope_full_res"] = 1000 * (time.perf_counter() - t)
    if full is not None:
        return RopeRuler(full["thickness_px"] * full["scale"], full["thickness_px"], full["contrast"],
                         ["rope_read_at_full_resolution"])
    from .profile import rope_profile_fwhm
    return RopeRuler(T, T, rope_profile_fwhm(frame.image, rope.polyline, rope.thickness_px)[1])


def rope_at_full_resolution(rgb: np.ndarray, camera, frame, rope) -> dict | None:
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

    Returns
    -------
    ``{"thickness_px", "contrast", "scale"}`` with ``scale`` the working / full-resolution pixel
    ratio; None when the photo is no larger than the working image or the band is not found
    again at the same place.
    """
    from .band import detect_rope
    from .profile import rope_profile_fwhm

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
    c = (np.asarray(rope.center_xy, np.float64) + 0.5) / (sx, sy) - 0.5 - (box[0], box[1])
    det = detect_rope(crop, None, pick_xy=(float(c[0]), float(c[1])), min_score=-np.inf)
    if not det or np.hypot(*(np.asarray(det.center_xy) - c)) > max(3 * T, 0.15 * L) + 4:
        return None
    if not 0.4 < det.thickness_px / max(T, 1e-6) < 2.5:
        return None
    contrast = rope_profile_fwhm(crop, det.polyline, det.thickness_px)[1]
    return {"thickness_px": float(det.thickness_px), "contrast": float(contrast), "scale": float(sx)}
