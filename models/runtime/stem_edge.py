"""The stem-edge network's runtime (network kind ``stem_edge``): where the roped stem's silhouette edges are at the rope.

The stem's width at the rope is read on the photo's gradients to a fraction of a pixel, but a
gradient says nothing about which side of it is the stem: a neighbouring trunk behind it, a
shadow or the ground's border are often stronger edges than the stem's own. This network looks
across the stem at the rope and says where its two edges are, to within a pixel or so; the
sub-pixel edge is then searched near it (``monodbh.toolkit.geometry.stem_edges``).

The patch (:func:`edge_patch`)
    Centred on a point of the stem at the rope ``center_xy`` (photo pixels), with ``along`` the
    stem's image direction (unit, down the stem) and ``width_px`` a rough width of the stem there:
    ``PATCH_W`` columns across the stem spanning ``PATCH_SPAN_W`` widths (``PATCH_COLS_PER_W``
    columns per width; the stem fills the middle half) and ``PATCH_H`` rows along it spanning
    ``PATCH_LEN_W`` widths. Channels: the normalised RGB (ImageNet mean/std) and a 0/1 flag of
    pixels inside the photo.

The output (:class:`StemEdgeFinder`)
    ``logits`` ``(1, 2, PATCH_W)``: for the left and the right edge, a softmax over "the edge is at
    column c" of the patch's middle row. :func:`decode_edge_logits` gives each edge's column (the
    probability-weighted mean around the most likely one) and its probability mass there.

Imported by ``monodbh.toolkit`` and by the network's modeling and training code (training cuts
its patches with :func:`edge_patch`); imports numpy and ``monodbh.models.runtime.common`` only.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from monodbh.models.runtime.common import OnnxPredictor, affine_patch, stack_feed

__all__ = ["PATCH_H", "PATCH_W", "PATCH_SPAN_W", "PATCH_LEN_W", "PATCH_COLS_PER_W", "patch_geometry",
           "edge_patch", "patch_feed", "decode_edge_logits", "EdgeEstimate", "StemEdgeFinder"]

# The patch's shape: structural facts of the trained network (its input), shared with training.
PATCH_H: int = 24            #: rows along the stem
PATCH_W: int = 128           #: columns across it
PATCH_SPAN_W: float = 2.0    #: stem widths across the patch
PATCH_LEN_W: float = 1.0     #: stem widths along it
PATCH_COLS_PER_W: float = PATCH_W / PATCH_SPAN_W


def patch_geometry(center_xy, along, width_px: float) -> np.ndarray:
    """Affine map ``(2, 3)`` from patch pixel ``(col, row)`` to photo pixel ``(x, y)``.

    Parameters
    ----------
    center_xy : (2,) the patch's centre (between its middle two columns and rows).
    along : (2,) image direction down the stem (normalised here).
    width_px : the stem's rough width (> 0, photo pixels).

    Examples
    --------
    >>> A = patch_geometry((100.0, 50.0), (0.0, 1.0), 64.0)
    >>> np.round(A @ [PATCH_W / 2 - 0.5, PATCH_H / 2 - 0.5, 1.0], 3).tolist()    # the centre
    [100.0, 50.0]
    >>> round(float(A[0, 0]), 3)          # photo pixels per column: 2 widths over 128 columns
    1.0
    """
    a = np.asarray(along, np.float64).reshape(2)
    n = float(np.linalg.norm(a))
    if not n > 0 or not width_px > 0:
        raise ValueError(f"patch_geometry: need a direction and a positive width, got {along}, {width_px}")
    a = a / n
    u = np.array([a[1], -a[0]])
    if u[0] < 0 or (u[0] == 0 and u[1] < 0):
        u = -u                               # columns run left -> right in the photo
    sx = width_px * PATCH_SPAN_W / PATCH_W   # photo pixels per column
    sy = width_px * PATCH_LEN_W / PATCH_H    # photo pixels per row
    c = np.asarray(center_xy, np.float64).reshape(2)
    o = c - (PATCH_W / 2 - 0.5) * sx * u - (PATCH_H / 2 - 0.5) * sy * a
    return np.array([[sx * u[0], sy * a[0], o[0]],
                     [sx * u[1], sy * a[1], o[1]]])


def edge_patch(rgb: np.ndarray, center_xy, along, width_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Cut the patch across the stem (see the module docstring).

    Parameters
    ----------
    rgb : (H, W, 3) uint8 undistorted photo.
    center_xy, along, width_px : as :func:`patch_geometry`.

    Returns
    -------
    (patch, inside): ``(PATCH_H, PATCH_W, 3)`` uint8 and ``(PATCH_H, PATCH_W)`` bool.
    """
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"edge_patch: expected an (H, W, 3) photo, got {rgb.shape}")
    A = patch_geometry(center_xy, along, width_px)
    return affine_patch(rgb, A, PATCH_W, PATCH_H, width_px * PATCH_SPAN_W / PATCH_W, width_px * PATCH_LEN_W / PATCH_H)


def patch_feed(patch: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """``(PATCH_H, PATCH_W, 3)`` uint8 + ``(PATCH_H, PATCH_W)`` bool -> ``(4, PATCH_H, PATCH_W)`` float32."""
    return stack_feed(patch, inside)


def decode_edge_logits(logits: np.ndarray, window: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """``(2, PATCH_W)`` logits -> ``(cols (2,), mass (2,))``.

    For each edge (left, right): its column, the probability-weighted mean within ``window``
    columns of the most likely one, and the probability mass there.

    Examples
    --------
    >>> z = np.full((2, PATCH_W), -20.0); z[0, 32] = z[0, 33] = 5.0; z[1, 96] = 5.0
    >>> cols, mass = decode_edge_logits(z); cols.round(2).tolist(), mass.round(3).tolist()
    ([32.5, 96.0], [1.0, 1.0])
    """
    z = np.asarray(logits, np.float64).reshape(2, -1)
    z = z - z.max(1, keepdims=True)
    p = np.exp(z)
    p /= p.sum(1, keepdims=True)
    cols, mass = np.zeros(2), np.zeros(2)
    for k in range(2):
        j = int(np.argmax(p[k]))
        lo, hi = max(0, j - window), min(p.shape[1], j + window + 1)
        w = p[k, lo:hi]
        cols[k] = float((np.arange(lo, hi) * w).sum() / max(w.sum(), 1e-12))
        mass[k] = float(w.sum())
    return cols, mass


@dataclass
class EdgeEstimate:
    """The stem's edges read by :class:`StemEdgeFinder`.

    Attributes
    ----------
    offsets_px : (2,) the left and right edge, photo pixels from ``center_xy`` across the stem
        (along ``across``, left negative).
    across : (2,) the unit photo direction of the offsets (left -> right).
    mass : (2,) each edge's probability mass within 3 columns of its most likely column.
    px_per_col : photo pixels per patch column (the network's resolution).
    """

    offsets_px: np.ndarray
    across: np.ndarray
    mass: np.ndarray
    px_per_col: float

    @property
    def width_px(self) -> float:
        """The width between the two edges (photo pixels)."""
        return float(self.offsets_px[1] - self.offsets_px[0])


class StemEdgeFinder(OnnxPredictor):
    """The stem-edge network (kind ``"stem_edge"``): the roped stem's two edges at the rope.

    Parameters
    ----------
    path : path, optional
        ONNX file (input ``patch`` ``(1, 4, PATCH_H, PATCH_W)``, output ``logits``
        ``(1, 2, PATCH_W)``); default the shipped ``models/stem_edge_int8.onnx``.
    threads, manifest, spin : as :class:`~monodbh.models.runtime.common.OnnxPredictor`.

    Examples
    --------
    >>> finder = StemEdgeFinder()                                        # doctest: +SKIP
    >>> est = finder.find(rgb, rope_xy, edges.along, edges.width_px)     # doctest: +SKIP
    >>> est.offsets_px, est.width_px                                     # doctest: +SKIP
    """

    kind = "stem_edge"

    def __init__(self, path: str | os.PathLike | None = None, threads: int = 2,
                 manifest: dict[str, Any] | None = None, *, spin: bool = False) -> None:
        super().__init__(self.kind, path, threads, manifest, spin=spin)

    def find(self, rgb: np.ndarray, center_xy, along, width_px: float) -> EdgeEstimate:
        """The two edges across the stem at ``center_xy`` (see the class docstring); the patch and
        its mirror image (left and right swapped) are averaged."""
        A = patch_geometry(center_xy, along, width_px)
        patch, inside = edge_patch(rgb, center_xy, along, width_px)
        x = patch_feed(patch, inside)[None]
        z = self.run({"patch": x})["logits"][0]
        zm = self.run({"patch": np.ascontiguousarray(x[..., ::-1])})["logits"][0]
        # the mirror's left edge is the right one, its columns reversed
        z = 0.5 * (z + zm[::-1, ::-1])
        cols, mass = decode_edge_logits(z)
        sx = float(np.hypot(A[0, 0], A[1, 0]))
        u = A[:, 0] / sx
        offsets = (cols + 0.5 - PATCH_W / 2) * sx
        return EdgeEstimate(offsets_px=offsets, across=u, mass=mass, px_per_col=sx)
