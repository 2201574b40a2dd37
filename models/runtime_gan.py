"""onnxruntime predictors of the two GAN networks: CDEN depth and the tree silhouette net.

numpy + cv2 + onnxruntime only (no torch): this module is on the measuring path.  The
pre-processing helpers here (:func:`letterbox`, :func:`crop_square`, the depth-code mapping)
are also what the training code uses, so train and inference see identical inputs.

Depth (:class:`DepthPredictor`)
    The photo is letterboxed to ``S x S`` (``S = 256``): resized with aspect kept so that
    ``max(W, H) = S`` (INTER_AREA), centred, padded with the mean colour; the tree mask likewise
    (area-resize, ``>= 0.5``, padded 0).  The network outputs a canonical log-depth code ``t``
    (:func:`depth_code_to_metric`); metric depth ``d = d_c(t) * fx_net / f_c`` with
    ``fx_net = fx_photo * S / max(W, H)`` and ``f_c = 0.8 S``.

Trees (:class:`TreePredictor`)
    A square window of side ``S_px = max(24, k * trunk_width_px)`` photo pixels centred on the
    stem-axis point is resampled to ``P x P`` (``P = 128``) together with the tree's mask; the
    network returns ``R_n`` (front depth) and ``G_n`` (thickness along each pixel's ray) in
    crop units: ``z1 = z_ref (1 + R_n S_px / f)``, ``z2 = z1 + c z_ref G_n S_px / f`` with ``c``
    the cosine of the pixel's ray to the optical axis (:func:`ray_cos_map`,
    :func:`silhouette_to_metric`; older files have ``thickness: "z"`` and no ``c``).
"""
from __future__ import annotations

import math
import os
from typing import Any

import cv2
import numpy as np

from monodbh.models.runtime import OnnxPredictor

__all__ = [
    "D_MIN", "D_MAX", "F_CANON_FRAC", "IMAGENET_MEAN", "IMAGENET_STD", "K_INFER", "MIN_CROP_PX",
    "depth_code_to_metric", "metric_to_depth_code", "letterbox_geometry", "letterbox",
    "unletterbox", "crop_side_px", "crop_affine", "crop_square", "normalize_rgb",
    "silhouette_to_metric", "silhouette_targets", "ray_cos_map", "DepthPredictor", "TreePredictor",
]

D_MIN: float = 0.5
D_MAX: float = 100.0
F_CANON_FRAC: float = 0.8
IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)
K_INFER: float = 4.0
MIN_CROP_PX: int = 24
_MEAN_RGB_U8 = tuple(float(v) for v in IMAGENET_MEAN * 255.0)


# --------------------------------------------------------------------------- depth code


def depth_code_to_metric(t: np.ndarray, fx_net: float, size: int = 256, d_min: float = D_MIN,
                         d_max: float = D_MAX, f_canon_frac: float = F_CANON_FRAC) -> np.ndarray:
    """Code ``t`` in [-1, 1] (any shape) -> metric depth (m), float32.

    ``fx_net``: the photo's focal length at network resolution (px); ``size``: network input side.
    """
    lo = math.log(d_min)
    # exp(lo + (t + 1) * 0.5 * (ln d_max - lo)) * fx_net / (f_canon_frac * size), step by step in
    # one buffer (the same float32 operations in the same order as the expression; no temporaries)
    d = np.asarray(np.add(np.asarray(t, np.float32), 1.0, dtype=np.float32))     # (0-d for a scalar)
    d *= 0.5
    d *= math.log(d_max) - lo
    d += lo
    np.exp(d, out=d)
    d *= fx_net / (f_canon_frac * size)
    return d if d.ndim else d[()]


def metric_to_depth_code(d: np.ndarray, fx_net: float, size: int = 256, d_min: float = D_MIN,
                         d_max: float = D_MAX, f_canon_frac: float = F_CANON_FRAC) -> np.ndarray:
    """Metric depth (m, > 0) -> code in [-1, 1] (clipped); inverse of :func:`depth_code_to_metric`."""
    lo = math.log(d_min)
    d_c = np.maximum(np.asarray(d, np.float64), 1e-6) * (f_canon_frac * size / fx_net)
    t = 2.0 * (np.log(d_c) - lo) / (math.log(d_max) - lo) - 1.0
    return np.clip(t, -1.0, 1.0).astype(np.float32)


# --------------------------------------------------------------------------- letterbox


def letterbox_geometry(width: int, height: int, size: int) -> tuple[float, int, int, int, int]:
    """``(scale, x0, y0, w, h)``: the photo becomes a ``w x h`` image at ``(x0, y0)`` in ``size^2``.

    ``scale = size / max(width, height)`` (``w = round(width * scale)``, likewise ``h``).
    """
    scale = size / max(width, height)
    w = min(size, max(1, int(round(width * scale))))
    h = min(size, max(1, int(round(height * scale))))
    return scale, (size - w) // 2, (size - h) // 2, w, h


def letterbox(img: np.ndarray, size: int, kind: str = "rgb") -> np.ndarray:
    """Letterbox ``img`` into ``(size, size[, C])``.

    ``kind``: ``"rgb"`` (uint8, INTER_AREA when shrinking, padded with the ImageNet mean colour),
    ``"mask"`` (bool/0-1: area-resized, ``>= 0.5``, padded 0; returned bool) or ``"nearest"``
    (any dtype, nearest, padded 0; for depth/label ground truth).
    """
    H, W = img.shape[:2]
    _, x0, y0, w, h = letterbox_geometry(W, H, size)
    if kind == "rgb":
        interp = cv2.INTER_AREA if w < W else cv2.INTER_LINEAR
        r = cv2.resize(img, (w, h), interpolation=interp) if (w, h) != (W, H) else img
        out = np.empty((size, size, img.shape[2]), img.dtype)
        out[...] = np.asarray(_MEAN_RGB_U8, np.float32).round().astype(img.dtype)
    elif kind == "mask":
        m = img.astype(np.float32)
        r = (cv2.resize(m, (w, h), interpolation=cv2.INTER_AREA) if (w, h) != (W, H) else m) >= 0.5
        out = np.zeros((size, size), bool)
    elif kind == "nearest":
        a = img if img.dtype != bool else img.astype(np.uint8)
        r = cv2.resize(a, (w, h), interpolation=cv2.INTER_NEAREST) if (w, h) != (W, H) else a
        r = r.astype(img.dtype)
        out = np.zeros((size, size) + img.shape[2:], img.dtype)
    else:
        raise ValueError(f"unknown letterbox kind {kind!r}")
    out[y0:y0 + h, x0:x0 + w] = r
    return out


def unletterbox(a: np.ndarray, width: int, height: int,
                interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """Inverse of :func:`letterbox` for a ``(size, size)`` map: cut the photo area, resize to ``(H, W)``."""
    size = a.shape[0]
    _, x0, y0, w, h = letterbox_geometry(width, height, size)
    return cv2.resize(np.ascontiguousarray(a[y0:y0 + h, x0:x0 + w]), (width, height),
                      interpolation=interpolation)


def normalize_rgb(rgb: np.ndarray, mean: np.ndarray = IMAGENET_MEAN,
                  std: np.ndarray = IMAGENET_STD) -> np.ndarray:
    """``(H, W, 3)`` uint8 -> ``(3, H, W)`` float32, ``(x / 255 - mean) / std``."""
    x = rgb.astype(np.float32) * (1.0 / 255.0)
    x = (x - np.asarray(mean, np.float32)) / np.asarray(std, np.float32)
    return np.ascontiguousarray(x.transpose(2, 0, 1))


# --------------------------------------------------------------------------- tree crops


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
    border: Any = _MEAN_RGB_U8 if (kind == "rgb" and img.ndim == 3) else 0
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


# --------------------------------------------------------------------------- predictors


class _GanPredictor(OnnxPredictor):
    """:class:`~monodbh.models.runtime.OnnxPredictor` plus the spec's normalisation constants."""

    def __init__(self, path: str | os.PathLike | None = None, threads: int = 2,
                 manifest: dict[str, Any] | None = None) -> None:
        super().__init__(self.kind, path, threads, manifest)
        self.extra = self.spec.get("extra", {})
        pre = (self.spec.get("preprocess") or [{}])[0]
        self.mean = np.asarray(pre.get("mean", IMAGENET_MEAN), np.float32)
        self.std = np.asarray(pre.get("std", IMAGENET_STD), np.float32)


class DepthPredictor(_GanPredictor):
    """Metric depth from one photo with the CDEN ONNX model (kind ``"cden"``).

    Parameters
    ----------
    path : path, optional
        ONNX file (fp32 or int8, spec in its metadata); default the shipped model of the
        manifest (``models/cden_int8.onnx``).
    threads : int
        onnxruntime intra-op threads.
    manifest : dict, optional
        Manifest to look the shipped model up in (default ``models/manifest.json``).
    flip_tta : bool
        Average the log-depth codes of the photo and of its mirror image (test-time
        augmentation; twice the network time). Measured (int8; docs/decisions/threads.md): held-out AbsRel
        0.316 -> 0.311, delta1 0.619 -> 0.624 (seed 9500, 64 photos); benchmark DBH MAE
        -0.24 +- 0.14 cm paired (seed 9000, 87 photos).
    """

    kind = "cden"

    def __init__(self, path: str | os.PathLike | None = None, threads: int = 2,
                 manifest: dict[str, Any] | None = None, flip_tta: bool = True) -> None:
        super().__init__(path, threads, manifest)
        self.flip_tta = bool(flip_tta)
        self.size = int(self.input_shape("image")[-1])
        dc = self.extra.get("depth_code", {})
        self.d_min = float(dc.get("d_min_m", D_MIN))
        self.d_max = float(dc.get("d_max_m", D_MAX))
        self.f_canon_frac = float(dc.get("f_canon_frac", F_CANON_FRAC))

    def feeds(self, rgb: np.ndarray, tree_mask: np.ndarray) -> dict[str, np.ndarray]:
        """Network inputs ``{"image": (1, 3, S, S), "mask": (1, 1, S, S)}`` for one photo."""
        img = normalize_rgb(letterbox(rgb, self.size, "rgb"), self.mean, self.std)[None]
        m = letterbox(np.asarray(tree_mask, bool), self.size, "mask").astype(np.float32)[None, None]
        return {"image": img, "mask": m}

    def fx_net(self, fx_px: float, width: int, height: int) -> float:
        """Photo focal length at network resolution: ``fx * S / max(W, H)``."""
        return float(fx_px) * self.size / max(width, height)

    def predict_code(self, rgb: np.ndarray, tree_mask: np.ndarray) -> np.ndarray:
        """Raw code ``(S, S)`` float32 in [-1, 1] (letterboxed network frame)."""
        return self.run(self.feeds(rgb, tree_mask))["depth_code"][0, 0]

    def predict(self, rgb: np.ndarray, tree_mask: np.ndarray, fx_px: float) -> np.ndarray:
        """Metric z-depth at photo resolution.

        Parameters
        ----------
        rgb : (H, W, 3) uint8
            Undistorted photo.
        tree_mask : (H, W) bool
            Union of tree instance masks.
        fx_px : float
            Horizontal focal length of ``rgb`` in pixels.

        Returns
        -------
        (H, W) float32
            Depth in metres (bilinear upsampling of the log-depth code).
        """
        H, W = rgb.shape[:2]
        if tree_mask.shape[:2] != (H, W):
            raise ValueError(f"tree_mask shape {tree_mask.shape} != photo {(H, W)}")
        t = unletterbox(self.predict_code(rgb, tree_mask), W, H)
        if self.flip_tta:
            # (cv2.flip: the same mirror copies as numpy's, 4x faster)
            m = np.asarray(tree_mask)
            m_f = cv2.flip(m.view(np.uint8), 1).view(bool) if m.dtype == bool else np.ascontiguousarray(m[:, ::-1])
            tf = unletterbox(self.predict_code(cv2.flip(np.ascontiguousarray(rgb), 1), m_f), W, H)
            t += tf[:, ::-1]
            t *= 0.5
        return depth_code_to_metric(t, self.fx_net(fx_px, W, H), self.size, self.d_min,
                                    self.d_max, self.f_canon_frac)


class TreePredictor(_GanPredictor):
    """Silhouette depth map (front depth, thickness) of one tree around a stem-axis point.

    Parameters
    ----------
    path : path, optional
        ONNX file with input ``crop`` ``(1, 4, P, P)`` and output ``silhouette`` (kind
        ``"treenet"``); default the shipped ``models/treenet_int8.onnx``.
    threads, manifest : as :class:`DepthPredictor`.
    """

    kind = "treenet"

    def __init__(self, path: str | os.PathLike | None = None, threads: int = 2,
                 manifest: dict[str, Any] | None = None) -> None:
        super().__init__(path, threads, manifest)
        self.size = int(self.input_shape("crop")[-1])
        self.k_default = float(self.extra.get("k_infer", K_INFER))
        self.min_crop_px = float(self.extra.get("min_crop_px", MIN_CROP_PX))
        #: "ray": G_n is the thickness along each pixel's ray; "z" (older files): in z
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
