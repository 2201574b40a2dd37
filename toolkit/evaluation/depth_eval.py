"""Metric depth maps for whole photos (``dbh depth``) and their scores on a ``dbh synth`` folder
(``dbh eval-depth``).

The depth network runs on the pipeline's undistorted, downscaled working image; its output is
resampled onto the original photo's (distorted) pixel grid, so a ``<stem>_depth.npy`` lines up
with the photo pixel for pixel. Scores: ``monodbh.models.training.depth_metrics`` (the training's
own), averaged over the photos.

Imported by ``monodbh.cli.depth_cmd``; imports the pipeline (its session and working image), the
depth metrics, ``toolkit.outputs.atomic`` and the dataset format.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from monodbh.models.training.depth_metrics import DEPTH_METRIC_KEYS, depth_metrics
from monodbh.toolkit.outputs.atomic import atomic_open

__all__ = ["photo_depth", "write_depth", "evaluate_depth", "print_depth_scores"]


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
    from monodbh.toolkit.config import MeasureConfig
    from monodbh.toolkit.frames import read_photo, work_frame

    tm = {}
    t = time.perf_counter()
    rgb = read_photo(path)
    H, W = rgb.shape[:2]
    cam_photo = camera.for_image(W, H)
    frame = work_frame(rgb, camera, MeasureConfig().work_long_side_px)
    img, cam = frame.image, frame.camera
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


def depth_file(out_dir: str | Path, photo: str) -> Path:
    """Where :func:`write_depth` puts the depth of ``photo``: ``<out_dir>/<stem>_depth.npy``
    (the name cut to fit the file system)."""
    from monodbh.toolkit.outputs.paths import fit_name

    return Path(out_dir) / fit_name(Path(photo).stem, "_depth.npy")


def write_depth(out_dir: str | Path, photo: str, depth: np.ndarray) -> Path:
    """Write ``<photo stem>_depth.npy`` (float32 metres, ``(H, W)``) in ``out_dir`` atomically.

    Returns
    -------
    Path
        The written file.
    """
    from monodbh.calib.errors import MonodbhError

    p = depth_file(out_dir, photo)
    try:
        with atomic_open(p, "wb") as f:
            np.save(f, depth.astype(np.float32))
    except OSError as exc:
        raise MonodbhError(f"{p}: cannot write ({exc.strerror or exc})") from None
    return p


def evaluate_depth(folder: str | Path, session, limit: int | None = None,
                   max_depth_m: float = 80.0) -> tuple[list[dict], list[float]]:
    """Score the depth network on the samples of a ``dbh synth`` folder.

    Parameters
    ----------
    folder : path
        A ``dbh synth`` folder (complete samples: ``.jpg``, ``.npz``, ``.json``).
    session : monodbh.toolkit.pipeline.Session
        Its segmenter and depth network run.
    limit : int, optional
        Score the first ``limit`` samples only.
    max_depth_m : float
        Score the pixels whose true depth is at most this (metres).

    Returns
    -------
    (list of dict, list of float)
        Per photo with valid pixels, :func:`~monodbh.models.training.depth_metrics.depth_metrics`
        of :func:`photo_depth` against the true depth; the depth network's milliseconds per photo.
    """
    from monodbh.models.synthetic.io import list_samples, read_sample

    from .synth_samples import camera_from_meta

    ms, times = [], []
    for i in list_samples(folder)[: limit or None]:
        s = read_sample(folder, i)
        d, tm = photo_depth(s["path"], camera_from_meta(s["meta"]), session)
        ms.append(depth_metrics(d, s["depth"], max_depth=max_depth_m))
        times.append(tm.get("depth", 0.0))
    return [m for m in ms if m], times


def print_depth_scores(ms: list[dict], title: str, console) -> None:
    """Print the mean of each metric over ``ms`` (:func:`evaluate_depth`), metric and median-scaled."""
    from rich.table import Table

    t = Table(title=title)
    t.add_column("")
    for k in DEPTH_METRIC_KEYS:
        t.add_column(k, justify="right")
    for prefix, name in (("", "metric"), ("ms_", "median-scaled")):
        t.add_row(name, *[f"{np.mean([x[prefix + k] for x in ms]):.3f}" for k in DEPTH_METRIC_KEYS])
    console.print(t)
