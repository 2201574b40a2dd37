"""Is the photo on its side? A light cue for photos turned 90 degrees without an EXIF orientation.

Lives here: :func:`sideways_score`, the difference between the photo's top-to-bottom and
left-to-right brightness (the sky, or the bright canopy gaps, are above the camera in an upright
forest photo). Imported by :mod:`monodbh.toolkit.pipeline`, which flags ``photo_maybe_sideways``
below :attr:`~monodbh.toolkit.config.MeasureConfig.sideways_score_max` (decision record
``docs/decisions/sideways-photo.md``); imports numpy and cv2.

The networks cannot tell: the segmenter finds upright "trunks" in a sideways forest photo too,
so a sideways photo is measured (another tree, or a branch) unless the user is told.
"""
from __future__ import annotations

import numpy as np

__all__ = ["sideways_score"]

_SIDE = 64          # the photo is reduced to _SIDE x _SIDE gray levels
_BAND = 16          # width of the border bands compared (a quarter of the side)


def sideways_score(rgb: np.ndarray) -> float:
    """How much brighter the photo is at its top than its bottom, less how much one side is
    brighter than the other (gray levels 0-255): positive for upright forest photos (sky above),
    negative when the light comes from a side, as in a photo turned 90 degrees.

    Parameters
    ----------
    rgb : (H, W, 3) uint8 or (H, W) uint8 image.

    Returns
    -------
    float
        ``(top - bottom) - |left - right|`` of the mean gray levels of the border quarters.

    Examples
    --------
    >>> sky = np.tile(np.linspace(255, 0, 64)[:, None], (1, 64)).astype(np.uint8)
    >>> sideways_score(sky) > 100, sideways_score(np.ascontiguousarray(np.rot90(sky))) < -100
    (True, True)
    """
    import cv2

    a = np.asarray(rgb)
    if a.ndim not in (2, 3) or a.dtype != np.uint8:
        raise ValueError(f"expected an (H, W[, 3]) uint8 image, got {a.dtype} {a.shape}")
    g = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY) if a.ndim == 3 else a
    g = cv2.resize(g, (_SIDE, _SIDE), interpolation=cv2.INTER_AREA).astype(np.float64)
    top, bottom = g[:_BAND].mean(), g[-_BAND:].mean()
    left, right = g[:, :_BAND].mean(), g[:, -_BAND:].mean()
    return float((top - bottom) - abs(left - right))
