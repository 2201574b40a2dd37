"""The depth network's runtime (network kind ``depth``; the CDEN architecture): metric depth of a photo.

The photo is letterboxed to ``S x S`` (``S = 256``, the network's input side, read from the
graph): resized with aspect kept so that ``max(W, H) = S`` (INTER_AREA), centred, padded with
the mean colour; the tree mask likewise (area-resize, ``>= 0.5``, padded 0). The network
outputs a canonical log-depth code ``t`` (:func:`depth_code_to_metric`); metric depth
``d = d_c(t) * fx_net / f_c`` with ``fx_net = fx_photo * S / max(W, H)`` and ``f_c = 0.8 S``.

Imported by ``monodbh.toolkit`` and the depth network's training code (the letterbox and the
depth code are shared so that training sees exactly the runtime's inputs); imports numpy, cv2
and ``monodbh.models.runtime.common`` only.
"""
from __future__ import annotations

import math
import os
from typing import Any

import cv2
import numpy as np

from monodbh.models.runtime.common import IMAGENET_MEAN, IMAGENET_STD, MEAN_RGB, OnnxPredictor, normalize_rgb

__all__ = ["D_MIN", "D_MAX", "F_CANON_FRAC", "depth_code_to_metric", "metric_to_depth_code",
           "letterbox_geometry", "letterbox", "unletterbox", "DepthPredictor"]

#: depth code range (m) and canonical focal length (fraction of the input side): structural
#: facts of the trained network (the manifest's ``extra.depth_code`` overrides them per file)
D_MIN: float = 0.5
D_MAX: float = 100.0
F_CANON_FRAC: float = 0.8


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
        out[...] = np.asarray(MEAN_RGB, np.float32).round().astype(img.dtype)
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


class DepthPredictor(OnnxPredictor):
    """Metric depth from one photo (network kind ``"depth"``, the CDEN architecture).

    Parameters
    ----------
    path : path, optional
        ONNX file (fp32 or int8, spec in its metadata); default the shipped model of the
        manifest (``models/depth_int8.onnx``).
    threads, manifest, spin : as :class:`~monodbh.models.runtime.common.OnnxPredictor`.
    flip_tta : bool
        Average the log-depth codes of the photo and of its mirror image (test-time
        augmentation, twice the network time; ``docs/decisions/threads.md``, mirror averaging).
    """

    kind = "depth"

    def __init__(self, path: str | os.PathLike | None = None, threads: int = 2,
                 manifest: dict[str, Any] | None = None, flip_tta: bool = True, *,
                 spin: bool = False) -> None:
        super().__init__(self.kind, path, threads, manifest, spin=spin)
        self.extra = self.spec.get("extra", {})
        pre = (self.spec.get("preprocess") or [{}])[0]
        self.mean = np.asarray(pre.get("mean", IMAGENET_MEAN), np.float32)
        self.std = np.asarray(pre.get("std", IMAGENET_STD), np.float32)
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
