"""Metric depth maps for whole photos (``dbh depth``) and their scoring (``dbh eval-depth``).

The depth network runs on the undistorted, downscaled working image; its output is resampled
onto the original photo's (distorted) pixel grid, so a ``<stem>_depth.npy`` lines up with the
photo pixel for pixel.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

__all__ = ["depth_metrics", "photo_depth", "DEPTH_METRIC_KEYS"]

DEPTH_METRIC_KEYS = ("absrel", "sqrel", "rmse", "rmse_log", "log10", "delta1", "delta2", "delta3")


def depth_metrics(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None,
                  max_depth: float = 80.0) -> dict[str, float]:
    """The paper's depth metrics on one image, metric and median-scaled (prefix ``ms_``).

    Parameters
    ----------
    pred, gt : (H, W) metres; pixels with ``0 < gt <= max_depth`` (and ``valid``) count.

    Returns
    -------
    dict (empty when no pixel is valid).

    Examples
    --------
    >>> g = np.full((4, 4), 2.0)
    >>> round(depth_metrics(g * 1.1, g)["absrel"], 3), round(depth_metrics(g * 1.1, g)["ms_absrel"], 3)
    (0.1, 0.0)
    """
    m = (gt > 0) & (gt <= max_depth) & np.isfinite(pred)
    if valid is not None:
        m &= valid
    if not m.any():
        return {}
    p = np.maximum(pred[m].astype(np.float64), 1e-3)
    g = gt[m].astype(np.float64)
    out = {}
    for prefix, q in (("", p), ("ms_", p * (np.median(g) / np.median(p)))):
        ratio = np.maximum(q / g, g / q)
        out[prefix + "absrel"] = float(np.mean(np.abs(q - g) / g))
        out[prefix + "sqrel"] = float(np.mean((q - g) ** 2 / g))
        out[prefix + "rmse"] = float(np.sqrt(np.mean((q - g) ** 2)))
        out[prefix + "rmse_log"] = float(np.sqrt(np.mean((np.log(q) - np.log(g)) ** 2)))
        out[prefix + "log10"] = float(np.mean(np.abs(np.log10(q) - np.log10(g))))
        for k in (1, 2, 3):
            out[prefix + f"delta{k}"] = float(np.mean(ratio < 1.25 ** k))
    return out


def _to_photo_grid(depth_work: np.ndarray, cam_photo, K_work: np.ndarray, step: int = 8) -> np.ndarray:
    """Resample a pinhole working-frame map onto the distorted photo pixel grid."""
    import cv2
    W, H = cam_photo.width, cam_photo.height
    xs = np.unique(np.r_[np.arange(0, W, step), W - 1]).astype(np.float64)
    ys = np.unique(np.r_[np.arange(0, H, step), H - 1]).astype(np.float64)
    gx, gy = np.meshgrid(xs, ys)
    uv = cam_photo.undistort_points(np.c_[gx.ravel(), gy.ravel()], K_new=K_work).reshape(len(ys), len(xs), 2)
    fx = np.interp(np.arange(W), xs, np.arange(len(xs))).astype(np.float32)
    fy = np.interp(np.arange(H), ys, np.arange(len(ys))).astype(np.float32)
    mx, my = np.meshgrid(fx, fy)
    mapx = cv2.remap(uv[..., 0].astype(np.float32), mx, my, cv2.INTER_LINEAR)
    mapy = cv2.remap(uv[..., 1].astype(np.float32), mx, my, cv2.INTER_LINEAR)
    return cv2.remap(depth_work.astype(np.float32), mapx, mapy, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


def photo_depth(path: str, camera, session) -> tuple[np.ndarray, dict]:
    """Metric z-depth ``(H, W)`` float32 of a photo from the depth network (canonical-camera
    mapping with the calibrated focal length; no rope rescaling). Returns (depth, timings_ms)."""
    from ..calib import load_photo
    from .pipeline import _work_image
    tm = {}
    t = time.perf_counter()
    rgb = load_photo(path)
    H, W = rgb.shape[:2]
    cam_photo = camera.for_image(W, H)
    img, cam, _, _ = _work_image(rgb, camera)
    tm["load"] = 1000 * (time.perf_counter() - t)
    t = time.perf_counter()
    seg = session.segmenter.predict(img, size=(img.shape[1], img.shape[0]))
    tm["segment"] = 1000 * (time.perf_counter() - t)
    t = time.perf_counter()
    d = session.depth.predict(img, seg.instance > 0, float(cam.K[0, 0]))
    tm["depth"] = 1000 * (time.perf_counter() - t)
    t = time.perf_counter()
    out = _to_photo_grid(d, cam_photo, cam.K)
    tm["resample"] = 1000 * (time.perf_counter() - t)
    return out, tm


def write_depth(out_dir: str | Path, photo: str, depth: np.ndarray) -> Path:
    """Write ``<stem>_depth.npy`` atomically; returns its path."""
    import os
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    p = out_dir / f"{Path(photo).stem}_depth.npy"
    tmp = p.with_name(p.name + ".tmp")
    with open(tmp, "wb") as f:
        np.save(f, depth.astype(np.float32))
    os.replace(tmp, p)
    return p
