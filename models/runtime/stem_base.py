"""The stem-base network's runtime (network kind ``stem_base``): where the roped stem meets the ground.

Where a stem meets the ground gives the photo's scale: the rope is 1.3 m above it, so the
angle between the rope and the base fixes the distance (single-view metrology). This network
reads the stem below the rope as a whole, where a classical edge tracker often loses it.

The strip (:func:`stem_strip`)
    From the stem's mid-point at the rope ``top_xy`` (photo pixels), along the stem's image
    direction ``along`` (unit, pointing down the stem) a straight strip of ``STRIP_LEN_W`` stem
    widths is cut, ``STRIP_SPAN_W`` stem widths across, and resampled to ``STRIP_H x STRIP_W``
    (rows down the stem, ``STRIP_ROWS_PER_W`` rows per stem width; row 0 is the rope).
    Channels: the normalised RGB (ImageNet mean/std) and a 0/1 flag of pixels inside the photo.

A second network (:class:`StemBaseNetFinder`, kind ``stem_base_net``, where shipped) reads the
same strip with ImageNet features; the finder asks it where the first sees no base. The first
was trained on the generator's look alone and finds far fewer bases on a look it never saw; the
second finds fewer on the default look but holds on others (``docs/decisions/stem-base.md``).

The output (:class:`StemBaseFinder`)
    ``logits`` ``(1, STRIP_H + 1)``: a softmax over "the base is at row r" (r = 0 .. STRIP_H-1)
    and a last class "no visible base in the strip" (hidden behind grass or bushes, outside the
    photo, or further down than the strip). The base row is the probability-weighted mean
    row around the most likely one; ``p_base`` its total probability.

Imported by ``monodbh.toolkit`` and by the stem-base network's modeling and training code
(``monodbh.models.training.stem_base`` cuts its strips with :func:`stem_strip`, so train and
inference cut identical strips); imports numpy, cv2 and ``monodbh.models.runtime.common`` only.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from monodbh.models.runtime.common import OnnxPredictor, affine_patch, stack_feed

__all__ = ["STRIP_H", "STRIP_W", "STRIP_ROWS_PER_W", "STRIP_SPAN_W", "STRIP_LEN_W",
           "strip_geometry", "stem_strip", "strip_feed", "strip_row_to_xy", "decode_base_logits",
           "BaseEstimate", "StemBaseFinder", "StemBaseNetFinder"]

# The strip's shape: structural facts of the trained network (its input), shared with training.
STRIP_H: int = 192           #: rows down the stem
STRIP_W: int = 48            #: columns across
STRIP_ROWS_PER_W: float = 10.0   #: rows per stem width (so the strip is 19.2 widths long)
STRIP_SPAN_W: float = 4.0    #: stem widths across the strip (the stem fills its middle quarter)
STRIP_LEN_W: float = STRIP_H / STRIP_ROWS_PER_W


def strip_geometry(top_xy, along, width_px: float) -> np.ndarray:
    """Affine map ``(2, 3)`` from strip pixel ``(col, row)`` to photo pixel ``(x, y)``.

    Parameters
    ----------
    top_xy : (2,) the stem's mid-point at the rope (strip row 0, middle column).
    along : (2,) image direction down the stem (normalised here).
    width_px : the stem's width at the rope in photo pixels (> 0).

    Examples
    --------
    >>> A = strip_geometry((100.0, 50.0), (0.0, 1.0), 20.0)
    >>> np.round(A @ [STRIP_W / 2 - 0.5, 10.0, 1.0], 3).tolist()   # 10 rows = one stem width down
    [100.0, 70.0]
    """
    a = np.asarray(along, np.float64).reshape(2)
    n = float(np.linalg.norm(a))
    if not n > 0 or not width_px > 0:
        raise ValueError(f"strip_geometry: need a direction and a positive width, got {along}, {width_px}")
    a = a / n
    u = np.array([a[1], -a[0]])           # across the stem (left -> right when along points down)
    sy = width_px / STRIP_ROWS_PER_W       # photo pixels per row
    sx = width_px * STRIP_SPAN_W / STRIP_W  # photo pixels per column
    t = np.asarray(top_xy, np.float64).reshape(2)
    # (col, row) -> t + (col + 0.5 - W/2) sx u + row sy a  (pixel centres at integers)
    return np.array([[sx * u[0], sy * a[0], t[0] + (0.5 - STRIP_W / 2) * sx * u[0]],
                     [sx * u[1], sy * a[1], t[1] + (0.5 - STRIP_W / 2) * sx * u[1]]])


def strip_row_to_xy(row: float, top_xy, along, width_px: float) -> np.ndarray:
    """Photo pixel ``(2,)`` on the strip's middle line at (fractional) strip ``row``."""
    A = strip_geometry(top_xy, along, width_px)
    return A @ np.array([STRIP_W / 2 - 0.5, float(row), 1.0])


def stem_strip(rgb: np.ndarray, top_xy, along, width_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Cut the strip below the rope (see the module docstring).

    Parameters
    ----------
    rgb : (H, W, 3) uint8 undistorted photo.
    top_xy, along, width_px : as :func:`strip_geometry`.

    Returns
    -------
    (strip, inside): ``(STRIP_H, STRIP_W, 3)`` uint8 (outside the photo: the mean colour) and
    ``(STRIP_H, STRIP_W)`` bool, True where the strip lies inside the photo.
    """
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"stem_strip: expected an (H, W, 3) photo, got {rgb.shape}")
    A = strip_geometry(top_xy, along, width_px)
    return affine_patch(rgb, A, STRIP_W, STRIP_H, width_px * STRIP_SPAN_W / STRIP_W, width_px / STRIP_ROWS_PER_W)


def strip_feed(strip: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """``(STRIP_H, STRIP_W, 3)`` uint8 + ``(STRIP_H, STRIP_W)`` bool -> ``(4, STRIP_H, STRIP_W)`` float32."""
    return stack_feed(strip, inside)


def decode_base_logits(logits: np.ndarray, window: int = 3) -> tuple[float, float]:
    """``(STRIP_H + 1,)`` logits -> ``(row, p_base)``.

    ``p_base`` is one minus the "no visible base" class's probability; ``row`` the
    probability-weighted mean row within ``window`` rows of the most likely row (NaN when the
    strip has no rows).

    Examples
    --------
    >>> z = np.full(STRIP_H + 1, -20.0); z[40] = 5.0; z[41] = 5.0
    >>> row, p = decode_base_logits(z); round(row, 2), round(p, 3)
    (40.5, 1.0)
    """
    z = np.asarray(logits, np.float64).reshape(-1)
    z = z - z.max()
    p = np.exp(z)
    p /= p.sum()
    rows = p[:-1]
    k = int(np.argmax(rows))
    lo, hi = max(0, k - window), min(len(rows), k + window + 1)
    w = rows[lo:hi]
    row = float((np.arange(lo, hi) * w).sum() / max(w.sum(), 1e-12))
    return row, float(1.0 - p[-1])


@dataclass
class BaseEstimate:
    """A stem base read by :class:`StemBaseFinder`.

    Attributes
    ----------
    xy : (2,) photo pixel of the base on the stem's image mid-line, or None (no visible base).
    p_base : probability that the strip shows the base.
    row : strip row of the base (fractional; rows of ``width_px / STRIP_ROWS_PER_W`` pixels).
    status : ``"found"`` or ``"none"`` (``p_base`` under the threshold).
    network : the kind of the network that read it (``"stem_base"``, or ``"stem_base_net"``: the second).
    """

    xy: np.ndarray | None
    p_base: float
    row: float
    status: str
    network: str = "stem_base"

    def __bool__(self) -> bool:
        return self.xy is not None


class StemBaseFinder(OnnxPredictor):
    """The stem-base network (kind ``"stem_base"``): where the roped stem meets the ground.

    Parameters
    ----------
    path : path, optional
        ONNX file (input ``strip`` ``(1, 4, STRIP_H, STRIP_W)``, output ``logits``
        ``(1, STRIP_H + 1)``); default the shipped ``models/stem_base_int8.onnx``.
    threads, manifest, spin : as :class:`~monodbh.models.runtime.common.OnnxPredictor`.
    threshold : float, optional
        ``p_base`` needed to report a base (default: the manifest's ``extra.p_threshold``,
        else 0.7; the pipeline's, ``docs/decisions/stem-base.md``).
    second : StemBaseFinder, optional
        Asked where this network sees no base (:meth:`find`); the shipped second network is a
        :class:`StemBaseNetFinder`.

    Examples
    --------
    >>> finder = StemBaseFinder()                                # doctest: +SKIP
    >>> est = finder.find(rgb, mid_xy, edges.along, edges.width_px)   # doctest: +SKIP
    >>> est.xy, est.p_base                                      # doctest: +SKIP
    """

    kind = "stem_base"

    def __init__(self, path: str | os.PathLike | None = None, threads: int = 2,
                 manifest: dict[str, Any] | None = None, threshold: float | None = None, *,
                 spin: bool = False, second: "StemBaseFinder | None" = None) -> None:
        super().__init__(self.kind, path, threads, manifest, spin=spin)
        extra = self.spec.get("extra", {}) or {}
        self.threshold = float(threshold if threshold is not None else extra.get("p_threshold", 0.7))
        self.second = second

    def logits(self, rgb: np.ndarray, top_xy, along, width_px: float) -> np.ndarray:
        """Raw ``(STRIP_H + 1,)`` logits for the strip below ``top_xy``."""
        strip, inside = stem_strip(rgb, top_xy, along, width_px)
        out = self.run({"strip": strip_feed(strip, inside)[None]})
        return out["logits"][0]

    def find(self, rgb: np.ndarray, top_xy, along, width_px: float) -> BaseEstimate:
        """The base below the rope (see the class docstring), flipped-strip averaging; where none
        is found, the ``second`` network's base if it finds one."""
        est = self._find(rgb, top_xy, along, width_px)
        if est or self.second is None:
            return est
        alt = self.second.find(rgb, top_xy, along, width_px)
        return alt if alt else est

    def _find(self, rgb: np.ndarray, top_xy, along, width_px: float) -> BaseEstimate:
        strip, inside = stem_strip(rgb, top_xy, along, width_px)
        x = strip_feed(strip, inside)[None]
        z = self.run({"strip": x})["logits"][0]
        z2 = self.run({"strip": np.ascontiguousarray(x[..., ::-1])})["logits"][0]
        row, p = decode_base_logits(0.5 * (z + z2))
        if p < self.threshold:
            return BaseEstimate(None, p, row, "none", self.kind)
        return BaseEstimate(strip_row_to_xy(row, top_xy, along, width_px), p, row, "found", self.kind)


class StemBaseNetFinder(StemBaseFinder):
    """The second stem-base network (kind ``"stem_base_net"``, ``models/stem_base_net_int8.onnx``):
    the same strip in and logits out as :class:`StemBaseFinder`, read with EfficientNet-Lite0's
    ImageNet features (``monodbh.models.modeling.stem_base.StemBaseNetL0``)."""

    kind = "stem_base_net"
