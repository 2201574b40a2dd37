"""The rope verifier's runtime (network kind ``rope_verifier``): is a candidate red band the rope?

A rope far away is thinner than a pixel. The mask-guided stem search
(``monodbh.toolkit.rope.stem_search``) finds rows of a segmented stem whose colour leans towards red,
but hand-made features (contrast, significance, width, height on the stem) tell such a row
from bark texture, shade or a branch only so well: on the benchmark, ropes a person sees at a
glance stayed unfound. This small network looks at the row itself.

The patch (:func:`band_patch`)
    Centred on a candidate band's middle ``center_xy``, along its direction ``direction``
    (unit, left to right across the stem), ``PATCH_W`` columns span ``PATCH_SPAN_W`` stem
    widths (``width_px``), so the stem fills the middle half whatever its size; the
    ``PATCH_H`` rows are photo pixels (a rope is 0.5-10 px thick, so rows are not rescaled),
    the band on row ``PATCH_H // 2``. Columns are averaged (anti-aliased) when a column spans
    more than 1.25 photo pixels: along the rope that only adds its signal up. Channels: the
    normalised RGB (ImageNet mean/std), a 0/1 flag of the candidate stem's instance mask, and
    one of pixels inside the photo.

The output (:class:`RopeVerifier`)
    ``logit`` ``(1, 1)``: log-odds that the band is the rope, from the patch and the stem
    search's own features (``side`` ``(1, N_SIDE)``: :data:`SIDE_FEATURES` of
    ``monodbh.toolkit.rope.stem_search.stem_band_features``).

Imported by ``monodbh.toolkit`` and by the rope verifier's modeling and training code (its
examples are cut with :func:`band_patch`, so train and inference cut identical patches); imports
numpy, cv2 and ``monodbh.models.runtime.common`` only.
"""
from __future__ import annotations

import math
import os
from typing import Any

import cv2
import numpy as np

from monodbh.models.runtime.common import (MEAN_RGB_U8, OnnxPredictor, affine_inside, affine_region, stack_feed,
                                           to_uint8)

__all__ = ["PATCH_H", "PATCH_W", "PATCH_SPAN_W", "SIDE_FEATURES", "N_SIDE", "patch_geometry", "band_patch",
           "patch_feed", "side_vector", "RopeVerifier"]

# The patch's shape and side features: structural facts of the trained network (its inputs).
PATCH_H: int = 32            #: rows across the band (photo pixels)
PATCH_W: int = 64            #: columns along the band
PATCH_SPAN_W: float = 2.0    #: stem widths along the band (the stem fills the middle half)
#: the stem search's features fed beside the patch (names of ``monodbh.toolkit.rope.stem_search.stem_band_features``)
SIDE_FEATURES: tuple[str, ...] = ("log_contrast", "log_zpix", "log_zprof", "log_width", "second", "red_shift",
                                  "h_lo", "h_hi", "main", "orange")
N_SIDE: int = len(SIDE_FEATURES)


def patch_geometry(center_xy, direction, width_px: float) -> np.ndarray:
    """Affine map ``(2, 3)`` from patch pixel ``(col, row)`` to photo pixel ``(x, y)``.

    Parameters
    ----------
    center_xy : (2,) the band's middle on the stem (patch centre).
    direction : (2,) image direction along the band (normalised here; flipped to point right).
    width_px : the stem's width along the band in photo pixels (> 0).

    Examples
    --------
    >>> A = patch_geometry((100.0, 50.0), (1.0, 0.0), 32.0)
    >>> np.round(A @ [PATCH_W / 2 - 0.5, PATCH_H // 2, 1.0], 3).tolist()
    [100.0, 50.0]
    """
    d = np.asarray(direction, np.float64).reshape(2)
    n = float(np.linalg.norm(d))
    if not n > 0 or not width_px > 0:
        raise ValueError(f"patch_geometry: need a direction and a positive width, got {direction}, {width_px}")
    d = d / n
    if d[0] < 0:
        d = -d
    v = np.array([-d[1], d[0]])                      # across the band, pointing down the photo
    sx = width_px * PATCH_SPAN_W / PATCH_W           # photo pixels per column
    c = np.asarray(center_xy, np.float64).reshape(2)
    o = c + (0.5 - PATCH_W / 2) * sx * d - (PATCH_H // 2) * v      # row PATCH_H // 2 on the band
    return np.array([[sx * d[0], v[0], o[0]], [sx * d[1], v[1], o[1]]])


def band_patch(rgb: np.ndarray, mask: np.ndarray | None, center_xy, direction,
               width_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cut the patch of a candidate band (see the module docstring).

    Parameters
    ----------
    rgb : (H, W, 3) uint8 photo (the pipeline's undistorted working image).
    mask : (H, W) bool, the candidate stem's instance mask, or None.
    center_xy, direction, width_px : as :func:`patch_geometry`.

    Returns
    -------
    (patch, stem, inside): ``(PATCH_H, PATCH_W, 3)`` uint8 (outside the photo: the mean
    colour), ``(PATCH_H, PATCH_W)`` bool stem mask and bool inside-the-photo flag.

    Examples
    --------
    >>> img = np.zeros((100, 200, 3), np.uint8); img[49:51, 80:120] = (200, 30, 30)
    >>> p, s, ins = band_patch(img, None, (100.0, 50.0), (1.0, 0.0), 40.0)
    >>> p.shape, bool(p[PATCH_H // 2, PATCH_W // 2, 0] > 100), bool(ins.all())
    ((32, 64, 3), True, True)
    """
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"band_patch: expected an (H, W, 3) photo, got {rgb.shape}")
    H, W = rgb.shape[:2]
    A = patch_geometry(center_xy, direction, width_px)
    sx = float(np.hypot(A[0, 0], A[1, 0]))
    x0, y0, x1, y1 = affine_region(A, PATCH_W, PATCH_H, sx, W, H)
    inside = affine_inside(A, PATCH_W, PATCH_H, W, H)
    out = np.empty((PATCH_H, PATCH_W, 3), np.uint8)
    out[...] = MEAN_RGB_U8
    stem = np.zeros((PATCH_H, PATCH_W), bool)
    if x1 <= x0 or y1 <= y0:
        return out, stem, inside
    roi = rgb[y0:y1, x0:x1].astype(np.float32)
    Ar = A.copy()
    Ar[:, 2] -= (x0, y0)
    if sx > 1.25:
        # anti-alias along the band only: resample at 1 px per column, then average columns
        k = int(math.ceil(sx))
        Af = Ar.copy()
        Af[:, 0] /= k
        wide = cv2.warpAffine(roi, Af, (PATCH_W * k, PATCH_H), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_REPLICATE)
        res = wide.reshape(PATCH_H, PATCH_W, k, 3).mean(2)
    else:
        res = cv2.warpAffine(roi, Ar, (PATCH_W, PATCH_H), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                             borderMode=cv2.BORDER_REPLICATE)
    out = to_uint8(res)
    out[~inside] = MEAN_RGB_U8
    if mask is not None:
        m = np.asarray(mask, np.uint8)[y0:y1, x0:x1]
        stem = cv2.warpAffine(m, Ar, (PATCH_W, PATCH_H), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=0).astype(bool) & inside
    return out, stem, inside


def patch_feed(patch: np.ndarray, stem: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """``(PATCH_H, PATCH_W, 3)`` uint8 + two ``(PATCH_H, PATCH_W)`` bool -> ``(5, PATCH_H, PATCH_W)`` float32."""
    return stack_feed(patch, stem, inside)


def side_vector(features: dict) -> np.ndarray:
    """``(N_SIDE,)`` float32 of :data:`SIDE_FEATURES` from a stem band's ``features`` dict."""
    return np.array([float(features.get(k, 0.0)) for k in SIDE_FEATURES], np.float32)


class RopeVerifier(OnnxPredictor):
    """The rope verifier (kind ``"rope_verifier"``): is this candidate band the rope?

    Parameters
    ----------
    path : path, optional
        ONNX file (inputs ``patch`` ``(1, 5, PATCH_H, PATCH_W)`` and ``side`` ``(1, N_SIDE)``,
        output ``logit`` ``(1, 1)``); default the shipped ``models/rope_verifier_int8.onnx``.
    threads, manifest, spin : as :class:`~monodbh.models.runtime.common.OnnxPredictor`.

    Examples
    --------
    >>> ver = RopeVerifier()                                              # doctest: +SKIP
    >>> ver.logits(rgb, [instance == b.tree_id for b in bands], bands)    # doctest: +SKIP
    """

    kind = "rope_verifier"

    def __init__(self, path: str | os.PathLike | None = None, threads: int = 2,
                 manifest: dict[str, Any] | None = None, *, spin: bool = False) -> None:
        super().__init__(self.kind, path, threads, manifest, spin=spin)

    def logits(self, rgb: np.ndarray, masks, bands) -> np.ndarray:
        """``(N,)`` log-odds for ``bands`` (objects with ``center_xy``, ``direction``,
        ``width_px`` and ``features``), each with its stem mask in ``masks`` (or None);
        the mean over the patch and its mirror image (left-right)."""
        if len(bands) == 0:
            return np.zeros(0, np.float32)
        out = np.empty(len(bands), np.float32)
        for k, (b, m) in enumerate(zip(bands, masks)):
            p, st, ins = band_patch(rgb, m, b.center_xy, b.direction, max(float(b.width_px), 1.0))
            x = patch_feed(p, st, ins)[None]
            s = side_vector(b.features)[None]
            z = self.run({"patch": x, "side": s})["logit"][0, 0]
            z2 = self.run({"patch": np.ascontiguousarray(x[..., ::-1]), "side": s})["logit"][0, 0]
            out[k] = 0.5 * (z + z2)
        return out
