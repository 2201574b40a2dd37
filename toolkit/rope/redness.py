"""Red-ness maps of a photo and the thin-line contrast on them; imported by the rope detectors
(band detector, stem search) and by the stem-edge geometry (the rope's gap in the edges).

* **Red-ness** ``F = max(0, R - max(G, B) - max(G - B, 0) / 2) / (R + G + B + 30)``: a
  chromaticity, so shading and exposure change it little; the ``G - B`` term lowers orange
  (sandy ground, flagging tape).
* **Thin-line contrast** (:func:`line_contrast`): after a blur along x, the red-ness of a pixel
  minus the larger of the red-ness ``d`` pixels above and below it. It is in red-ness units at
  every scale, is zero on the edges of red blobs and on evenly reddish bark, and answers to bands
  up to ~60 deg from horizontal, so vertical paint marks and hanging rope ends give little.
"""
from __future__ import annotations

import cv2
import numpy as np

__all__ = ["red_shift_map", "redness_map", "line_contrast"]


def red_shift_map(rgb: np.ndarray, offset: float = 30.0) -> np.ndarray:
    """Unclipped red chromaticity ``(R - max(G, B) - max(G - B, 0) / 2) / (R + G + B + offset)``.

    Negative on green, grey and blue pixels, so a rope thinner than a pixel still raises the
    mean of its row on a greenish or hazy trunk, where :func:`redness_map` (this map clipped at
    0) is 0 on the rope and on the bark alike (the stem search's reading for the rope verifier).

    Parameters
    ----------
    rgb : (H, W, 3) uint8 RGB.
    offset : damps the noisy chromaticity of dark pixels.

    Returns
    -------
    (H, W) float32 in (-1, 1).

    Examples
    --------
    >>> px = np.array([[[111, 127, 113], [105, 106, 95]]], np.uint8)   # bark, rope row
    >>> m = red_shift_map(px)
    >>> bool(m[0, 1] > m[0, 0]), float(redness_map(px).max())
    (True, 0.0)
    """
    R, G, B = cv2.split(rgb)
    # (in place where possible: a fresh 8 MB array per step costs its page faults, 1600 px photo)
    num = cv2.subtract(R, cv2.max(G, B), dtype=cv2.CV_32F)              # signed
    cv2.addWeighted(num, 1.0, cv2.subtract(G, B), -0.5, 0.0, dst=num, dtype=cv2.CV_32F)   # G - B saturates at 0
    den = cv2.addWeighted(R, 1.0, G, 1.0, float(offset), dtype=cv2.CV_32F)
    cv2.add(den, B, dst=den, dtype=cv2.CV_32F)
    return cv2.divide(num, den, dst=num)


def redness_map(rgb: np.ndarray, offset: float = 30.0) -> np.ndarray:
    """Red chromaticity ``max(0, R - max(G, B) - max(G - B, 0) / 2) / (R + G + B + offset)``.

    :func:`red_shift_map` clipped at 0, so that a grey band between green leaves is no "redder"
    than its neighbours.

    Parameters
    ----------
    rgb : (H, W, 3) uint8 RGB.
    offset : damps the noisy chromaticity of dark pixels.

    Returns
    -------
    (H, W) float32 in [0, 1).
    """
    m = red_shift_map(rgb, offset)
    return np.maximum(m, 0.0, out=m)


def line_contrast(F: np.ndarray, ds: tuple[int, ...] = (2, 3), sigma_x: float = 2.0,
                  sigma_y: float = 0.7) -> np.ndarray:
    """Contrast of thin, horizontal-ish bright lines in ``F``.

    ``max_d min(G(y) - G(y - d), G(y) - G(y + d))`` with ``G`` = ``F`` blurred anisotropically
    (``sigma_x`` along the line, ``sigma_y`` across), clipped at 0.

    Parameters
    ----------
    F : (H, W) float32.
    ds : vertical offsets in pixels (about the half-thickness plus one).
    sigma_x, sigma_y : the blur along and across the line, pixels.

    Returns
    -------
    (H, W) float32 >= 0, in the units of ``F``.
    """
    G = cv2.GaussianBlur(F, (0, 0), sigmaX=sigma_x, sigmaY=sigma_y)
    H = G.shape[0]
    out = np.zeros_like(G)
    abuf, bbuf = np.empty_like(G), np.empty_like(G)      # (reused: no fresh pages per step)
    for d in ds:
        if 2 * d >= H:
            continue
        n = H - 2 * d
        a = cv2.subtract(G[d:H - d], G[:n], dst=abuf[:n])
        b = cv2.subtract(G[d:H - d], G[2 * d:], dst=bbuf[:n])
        cv2.min(a, b, dst=a)
        o = out[d:H - d]
        cv2.max(o, a, dst=o)
    return out
