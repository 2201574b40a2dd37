"""The tree network's runtime (network kind ``tree``): the silhouette depth map of one stem.

A square window of side ``S_px = max(24, k * trunk_width_px)`` photo pixels centred on the
stem-axis point is resampled to ``P x P`` (``P = 128``, the network's input side, read from the
graph) together with the tree's mask; the network returns ``R_n`` (front depth) and ``G_n``
(thickness along each pixel's ray) in crop units: ``z1 = z_ref (1 + R_n S_px / f)``,
``z2 = z1 + c z_ref G_n S_px / f`` with ``c`` the cosine of the pixel's ray to the optical axis
(:func:`ray_cos_map`, :func:`silhouette_to_metric`; older files with ``thickness: "z"``
predict the thickness in z, without ``c``).

Imported by ``monodbh.toolkit`` and the tree network's training code (the crop and the
silhouette units are shared so that training sees exactly the runtime's inputs); imports
numpy, cv2 and ``monodbh.models.runtime.common`` only.
"""
from __future__ import annotations

import math
import os
from typing import Any

import cv2
import numpy as np

from monodbh.models.runtime.common import IMAGENET_MEAN, IMAGENET_STD, MEAN_RGB, OnnxPredictor, normalize_rgb

__all__ = ["K_INFER", "MIN_CROP_PX", "crop_side_px", "crop_affine", "crop_square", "ray_cos_map",
           "silhouette_targets", "silhouette_to_metric", "TreePredictor"]

#: crop side / trunk width, and the smallest crop side (photo px): structural facts of the trained
#: network (it was trained on k in U[3, 6]; the manifest's ``extra`` overrides them per file)
K_INFER: float = 4.0
MIN_CROP_PX: int = 24


def crop_side_px(trunk_width_px: float, k: float = K_INFER, min_px: float = MIN_CROP_PX) -> float:
    """Crop side ``S = max(min_px, k * trunk_width_px)`` in photo pixels."""
    return float(max(min_px, k * float(trunk_width_px)))


def crop_affine(center_xy: tuple[float, float], side_px: float, out_px: int) -> np.ndarray:
    """2x3 matrix mapping photo pixel coordinates to crop pixel coordinates (cv2 convention).

    Pixel centres are at integer coordinates; the crop covers the continuous window
    ``[cx - S/2, cx + S/2]`` so that crop pixel ``j`` has its centre at photo
    ``x = cx + (j + 0.5 - P/2) * S / P`` (same for rows).
    """
    cx, cy = center_xy
    a = out_px / side_px
    return np.array([[a, 0.0, -cx * a + out_px / 2.0 - 0.5],
                     [0.0, a, -cy * a + out_px / 2.0 - 0.5]], np.float64)


def crop_square(img: np.ndarray, center_xy: tuple[float, float], side_px: float, out_px: int,
                kind: str = "rgb") -> np.ndarray:
    """Resample the square window (:func:`crop_affine`) of ``img`` to ``out_px x out_px``.

    ``kind``: ``"rgb"`` (bilinear, border = ImageNet mean colour, anti-aliased when shrinking),
    ``"mask"`` (bool; resampled as float like rgb, ``>= 0.5``, border 0) or ``"nearest"``
    (any dtype, e.g. depths; border 0).  Only the needed region of ``img`` is touched.
    """
    H, W = img.shape[:2]
    cx, cy = float(center_xy[0]), float(center_xy[1])
    shrink = side_px / out_px
    pad = int(math.ceil(2 * max(shrink, 1.0))) + 2
    x0 = int(math.floor(cx - side_px / 2)) - pad
    y0 = int(math.floor(cy - side_px / 2)) - pad
    x1 = int(math.ceil(cx + side_px / 2)) + pad
    y1 = int(math.ceil(cy + side_px / 2)) + pad
    if kind not in ("rgb", "mask", "nearest"):
        raise ValueError(f"unknown crop kind {kind!r}")
    border: Any = MEAN_RGB if (kind == "rgb" and img.ndim == 3) else 0
    if kind == "nearest" and img.dtype == bool:
        return crop_square(img.astype(np.uint8), center_xy, side_px, out_px, kind).astype(bool)
    dtype = img.dtype if kind == "nearest" else np.float32
    roi = np.empty((y1 - y0, x1 - x0) + img.shape[2:], dtype)
    roi[...] = border
    xa, ya, xb, yb = max(x0, 0), max(y0, 0), min(x1, W), min(y1, H)
    if xb > xa and yb > ya:
        roi[ya - y0:yb - y0, xa - x0:xb - x0] = img[ya:yb, xa:xb]
    if kind != "nearest" and shrink > 1.25:
        sig = 0.5 * math.sqrt(shrink * shrink - 1.0)
        roi = cv2.GaussianBlur(roi, (0, 0), sigmaX=sig, sigmaY=sig, borderType=cv2.BORDER_REPLICATE)
    M = crop_affine((cx - x0, cy - y0), side_px, out_px)
    interp = cv2.INTER_NEAREST if kind == "nearest" else cv2.INTER_LINEAR
    out = cv2.warpAffine(roi, M, (out_px, out_px), flags=interp, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=border)
    if kind == "rgb":
        return np.clip(out + 0.5, 0, 255).astype(img.dtype) if img.dtype == np.uint8 else out
    if kind == "mask":
        return out >= 0.5
    return out


def ray_cos_map(crop_box: tuple[float, float, float], out_px: int, K: np.ndarray) -> np.ndarray:
    """``(P, P)`` float32: cosine of the angle between each crop pixel's ray and the optical axis.

    ``crop_box = (x0, y0, S)`` as returned by :meth:`TreePredictor.predict` (crop pixel ``(i, j)``
    has its centre at photo ``(x0 + (j + 0.5) S / P, y0 + (i + 0.5) S / P)``); ``K`` the (3, 3)
    intrinsics of the undistorted photo.  A length along a pixel's ray times this cosine is its
    extent in z.
    """
    x0, y0, S = (float(v) for v in crop_box)
    K = np.asarray(K, np.float64)
    g = (np.arange(out_px) + 0.5) * S / out_px
    xn = (x0 + g - K[0, 2]) / K[0, 0]
    yn = (y0 + g - K[1, 2]) / K[1, 1]
    return (1.0 / np.sqrt(1.0 + xn[None, :] ** 2 + yn[:, None] ** 2)).astype(np.float32)


def silhouette_targets(z1: np.ndarray, z2: np.ndarray, z_ref: float, side_px: float,
                       fx_px: float, cos_map: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Metric ``z1, z2`` -> ``(R_n, G_n)`` crop units (inverse of :func:`silhouette_to_metric`).

    With ``cos_map`` (:func:`ray_cos_map`, same shape) the thickness is the one along each
    pixel's ray, ``(z2 - z1) / cos``: what a crop shows does not tell where in the photo it was
    cut, so the network predicts the length along the ray, which does not depend on that (the z
    extent of a round stem 35 deg off the optical axis is 18 % less than its diameter).
    """
    u = fx_px / (z_ref * side_px)
    g = (z2 - z1) if cos_map is None else (z2 - z1) / np.maximum(cos_map, 1e-3)
    return ((z1 - z_ref) * u).astype(np.float32), (g * u).astype(np.float32)


def silhouette_to_metric(R_n: np.ndarray, G_n: np.ndarray, z_ref: float, side_px: float,
                         fx_px: float, cos_map: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(R_n, G_n)`` -> metric front and back depths ``(z_front, z_back)`` (m, z along the axis).

    ``z_front = z_ref (1 + R_n S / f)``, ``z_back = z_front + z_ref G_n S / f`` (times ``cos_map``
    when ``G_n`` is the thickness along the rays, see :func:`silhouette_targets`).
    """
    m = z_ref * side_px / fx_px
    zf = z_ref + np.asarray(R_n, np.float32) * m
    g = np.asarray(G_n, np.float32) * m
    if cos_map is not None:
        g = g * cos_map
    return zf.astype(np.float32), (zf + g).astype(np.float32)


class TreePredictor(OnnxPredictor):
    """Silhouette depth map (front depth, thickness) of one tree around a stem-axis point
    (network kind ``"tree"``).

    Parameters
    ----------
    path : path, optional
        ONNX file with input ``crop`` ``(1, 4, P, P)`` and output ``silhouette``; default the
        shipped ``models/tree_int8.onnx``.
    threads, manifest, spin : as :class:`~monodbh.models.runtime.common.OnnxPredictor`.
    """

    kind = "tree"

    def __init__(self, path: str | os.PathLike | None = None, threads: int = 2,
                 manifest: dict[str, Any] | None = None, *, spin: bool = False) -> None:
        super().__init__(self.kind, path, threads, manifest, spin=spin)
        self.extra = self.spec.get("extra", {})
        pre = (self.spec.get("preprocess") or [{}])[0]
        self.mean = np.asarray(pre.get("mean", IMAGENET_MEAN), np.float32)
        self.std = np.asarray(pre.get("std", IMAGENET_STD), np.float32)
        self.size = int(self.input_shape("crop")[-1])
        self.k_default = float(self.extra.get("k_infer", K_INFER))
        self.min_crop_px = float(self.extra.get("min_crop_px", MIN_CROP_PX))
        #: "ray": G_n is the thickness along each pixel's ray; "z" (older files without the key): in z
        self.thickness = str(self.extra.get("thickness", "z"))

    def feeds(self, rgb: np.ndarray, instance_mask: np.ndarray, center_xy: tuple[float, float],
              side_px: float) -> dict[str, np.ndarray]:
        """``{"crop": (1, 4, P, P)}`` for the window of side ``side_px`` centred at ``center_xy``."""
        c = crop_square(rgb, center_xy, side_px, self.size, "rgb")
        m = crop_square(np.asarray(instance_mask, bool), center_xy, side_px, self.size, "mask")
        x = np.concatenate([normalize_rgb(c, self.mean, self.std),
                            m.astype(np.float32)[None]], 0)[None]
        return {"crop": np.ascontiguousarray(x)}

    def predict(self, rgb: np.ndarray, instance_mask: np.ndarray, center_xy: tuple[float, float],
                trunk_width_px: float, fx_px: float, k: float | None = None
                ) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float]]:
        """Predict the tree's silhouette depth map around ``center_xy``.

        Parameters
        ----------
        rgb : (H, W, 3) uint8
            Undistorted photo.
        instance_mask : (H, W) bool
            This tree's mask.
        center_xy : (x, y)
            Stem-axis point (e.g. the rope centre), photo pixels.
        trunk_width_px : float
            Apparent trunk width at ``center_xy`` (px).
        fx_px : float
            Focal length (px); not needed for the crop units, kept for symmetry with
            :meth:`to_metric`.
        k : float, optional
            Crop side / trunk width (default 4, the training distribution is U[3, 6]).

        Returns
        -------
        R_n, G_n : (P, P) float32
            Front depth and thickness in crop units; meaningful only inside the crop's mask.
        crop_box : (x0, y0, side)
            Window in photo pixels (pixel centres at integer coordinates): ``x0 = cx - side/2``,
            ``y0 = cy - side/2``; crop pixel ``(i, j)`` has its centre at photo
            ``(x0 + (j + 0.5) * side / P, y0 + (i + 0.5) * side / P)``.
        """
        del fx_px
        side = crop_side_px(trunk_width_px, self.k_default if k is None else k, self.min_crop_px)
        out = self.run(self.feeds(rgb, instance_mask, center_xy, side))["silhouette"][0]
        cx, cy = float(center_xy[0]), float(center_xy[1])
        return (out[0].astype(np.float32), out[1].astype(np.float32),
                (cx - side / 2, cy - side / 2, side))

    def to_metric(self, R_n: np.ndarray, G_n: np.ndarray, z_ref: float,
                  crop_box: tuple[float, float, float], fx_px: float, K: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Metric ``(z_front, z_back)`` (m) from :meth:`predict` outputs and the axis depth ``z_ref``.

        ``K``: (3, 3) intrinsics of the photo the crop was cut from; needed by models whose
        thickness is along the rays (``self.thickness == "ray"``, the manifest's ``thickness``).
        """
        cos = None
        if self.thickness == "ray":
            if K is None:
                raise ValueError("this tree network predicts thickness along the rays: to_metric needs K")
            cos = ray_cos_map(crop_box, np.asarray(R_n).shape[-1], K)
        return silhouette_to_metric(R_n, G_n, z_ref, crop_box[2], fx_px, cos)
