"""Intrinsic calibration from photos of a chessboard or ChArUco board.

Pipeline (:func:`calibrate`): read every photo (EXIF-upright, gray), find the board on a
downscaled copy and refine the corners at full resolution (:func:`~monodbh.calib.board.detect_board`,
a small thread pool; OpenCV releases the GIL), calibrate with ``cv2.calibrateCameraExtended``
(``cv2.calibrateCameraROExtended`` for boards that are not quite flat), drop views whose
reprojection error is an outlier and calibrate again, then score the coverage of the image
like ROS ``camera_calibration``.
"""
from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np

from .board import DETECTORS, Board, Detection, detect_board
from .camera import CalibrationInfo, Camera
from .coverage import coverage_advice, coverage_scores, view_parameters
from .errors import CalibrationError
from .photo import load_photo, read_image_size

__all__ = ["calibrate", "detect_views", "calibrate_views", "CalibrationResult", "ViewResult",
           "STD_NAMES"]

#: Order of ``cv2.calibrateCameraExtended``'s ``stdDeviationsIntrinsics``.
STD_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6",
             "s1", "s2", "s3", "s4", "tauX", "tauY")
_MIN_IMAGE_SIDE = 32
_THUMB_SIDE = 1600


@dataclass
class ViewResult:
    """One input image of a calibration.

    Attributes
    ----------
    name : str
        File name (or ``"image N"`` for arrays).
    status : str
        ``"used"``, ``"rejected"`` (outlier, see ``reason``) or ``"failed"`` (no board).
    reason : str or None
        Why the view is not used.
    detection : Detection or None
        Corners found, full-resolution pixels.
    error_px : float or None
        RMS reprojection error of the view under the final calibration (rejected views are
        re-posed with ``solvePnP`` to get it).
    rvec, tvec : numpy.ndarray or None
        (3,) board pose in the camera frame (Rodrigues vector, metres).
    coverage : tuple of float or None
        ROS ``(X, Y, size, skew)`` of the view.
    residuals : numpy.ndarray or None
        (N, 2) reprojected minus detected corner positions, pixels.
    thumbnail : numpy.ndarray or None
        (h, w) uint8 gray copy at most 1600 px wide (``keep_images=True`` only).
    """

    name: str
    status: str = "failed"
    reason: Optional[str] = None
    detection: Optional[Detection] = None
    error_px: Optional[float] = None
    rvec: Optional[np.ndarray] = None
    tvec: Optional[np.ndarray] = None
    coverage: Optional[tuple] = None
    residuals: Optional[np.ndarray] = None
    thumbnail: Optional[np.ndarray] = None


@dataclass
class CalibrationResult:
    """Outcome of :func:`calibrate`.

    Attributes
    ----------
    camera : Camera
        Calibrated camera (``info`` filled for cam.yaml).
    rms : float
        RMS reprojection error over all used corners, pixels.
    views : list of ViewResult
        Every input image, in input order.
    std : dict
        Standard deviations of the intrinsics (``fx``, ``fy``, ``cx``, ``cy``, ``k1``...),
        pixels or unitless, from ``calibrateCameraExtended``.
    coverage : list of CoverageScore
        ROS-style X, Y, size, skew coverage of the used views.
    advice : list of str
        Suggestions when the coverage or the number of views is poor.
    board : Board
        The board.
    timings : dict
        Seconds spent in ``detect`` and ``calibrate``.
    """

    camera: Camera
    rms: float
    views: list
    std: dict
    coverage: list
    advice: list
    board: Board
    timings: dict = field(default_factory=dict)

    @property
    def used(self) -> list:
        return [v for v in self.views if v.status == "used"]

    @property
    def rejected(self) -> list:
        return [v for v in self.views if v.status != "used"]

    def to_dict(self) -> dict:
        """JSON-serialisable summary (numbers rounded to what matters)."""
        c = self.camera
        return {
            "image_size": list(c.image_size),
            "board": self.board.describe(),
            "rms_px": self.rms,
            "K": c.K.tolist(),
            "dist": c.dist.tolist(),
            "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy,
            "std": self.std,
            "views_used": len(self.used),
            "views_rejected": len(self.rejected),
            "views": [{"file": v.name, "status": v.status, "reason": v.reason,
                       "error_px": v.error_px,
                       "corners": None if v.detection is None else int(len(v.detection.ids))}
                      for v in self.views],
            "coverage": {s.name: {"min": s.min, "max": s.max, "progress": s.progress}
                         for s in self.coverage},
            "advice": list(self.advice),
            "timings_s": dict(self.timings),
        }


def _name_of(img: Any, i: int) -> str:
    if isinstance(img, (str, os.PathLike)):
        return str(img)
    return f"image {i}"


def _check_sizes(images: Sequence[Any], names: list[str]) -> tuple[int, int]:
    sizes = []
    for img, name in zip(images, names):
        if isinstance(img, np.ndarray):
            if img.ndim not in (2, 3) or img.dtype != np.uint8:
                raise ValueError(f"{name}: arrays must be (H, W) or (H, W, 3) uint8")
            sizes.append((int(img.shape[1]), int(img.shape[0])))
        elif isinstance(img, (str, os.PathLike)):
            sizes.append(read_image_size(img))
        else:
            raise TypeError(f"images must be paths or numpy arrays, got {type(img).__name__}")
    for (w, h), name in zip(sizes, names):
        if min(w, h) < _MIN_IMAGE_SIDE:
            raise CalibrationError(f"{name}: image is {w}x{h} px, too small to show a "
                                   f"calibration board")
    distinct = sorted(set(sizes), key=lambda s: -sizes.count(s))
    if len(distinct) > 1:
        main = distinct[0]
        odd = [n for n, s in zip(names, sizes) if s != main]
        shown = ", ".join(f"{Path(n).name} ({s[0]}x{s[1]})"
                          for n, s in zip(names, sizes) if s != main)
        if len(odd) > 4:
            shown = ", ".join(shown.split(", ")[:4]) + f", ... ({len(odd)} in all)"
        raise CalibrationError(f"images have mixed sizes: {sizes.count(main)} are "
                               f"{main[0]}x{main[1]} but {shown}; calibrate with photos of one "
                               f"size and orientation")
    return sizes[0]


def _to_gray(img: Any) -> np.ndarray:
    if isinstance(img, np.ndarray):
        if img.ndim == 2:
            return np.ascontiguousarray(img)
        import cv2

        return cv2.cvtColor(np.ascontiguousarray(img[:, :, :3]), cv2.COLOR_RGB2GRAY)
    return load_photo(img, gray=True)


def _thumb(gray: np.ndarray) -> np.ndarray:
    import cv2

    h, w = gray.shape
    s = max(h, w) / _THUMB_SIDE
    if s <= 1:
        return gray.copy()
    return cv2.resize(gray, (int(round(w / s)), int(round(h / s))), interpolation=cv2.INTER_AREA)


def detect_views(images: Sequence[Any], board: Board, *, names: Optional[Sequence[str]] = None,
                 detector: str = "auto", max_side: int = 1000,
                 subpix_win: Optional[int] = None, subpix_iters: int = 40,
                 subpix_eps: float = 1e-3, threads: Optional[int] = None,
                 progress: Optional[Callable[[int, int, str], None]] = None,
                 keep_images: bool = False) -> tuple[list[ViewResult], tuple[int, int]]:
    """Read the images and find the board in each (parallel).

    Parameters
    ----------
    images : sequence of path or numpy.ndarray
        Photo files, or ``(H, W)`` gray / ``(H, W, 3)`` RGB uint8 arrays; all the same size.
    board : Board
        The board.
    names : sequence of str, optional
        Display names (default: the paths, or ``"image N"``).
    detector, max_side, subpix_win, subpix_iters, subpix_eps
        See :func:`~monodbh.calib.board.detect_board`.
    threads : int, optional
        Worker threads (default ``min(4, cpu_count)``).
    progress : callable, optional
        Called as ``progress(done, total, name)`` after each image.
    keep_images : bool, optional
        Keep a gray thumbnail per view (for debug overlays).

    Returns
    -------
    views : list of ViewResult
        In input order; ``status`` is ``"used"`` where the board was found.
    image_size : tuple of int
        ``(width, height)``.

    Raises
    ------
    PhotoError
        An image cannot be read.
    CalibrationError
        Mixed sizes or images too small.
    """
    if not isinstance(board, Board):
        raise TypeError(f"board must be a Board, got {type(board).__name__}")
    if detector not in DETECTORS:
        raise ValueError(f"detector must be one of {DETECTORS}, got {detector!r}")
    images = list(images)
    if not images:
        raise CalibrationError("no images given")
    names = [_name_of(im, i) for i, im in enumerate(images)] if names is None else list(names)
    if len(names) != len(images):
        raise ValueError("names must have one entry per image")
    size = _check_sizes(images, names)
    n = len(images)
    threads = max(1, min(threads or min(4, os.cpu_count() or 1), n))

    def work(i: int) -> ViewResult:
        gray = _to_gray(images[i])
        if (gray.shape[1], gray.shape[0]) != size:
            raise CalibrationError(f"{names[i]}: decoded image is {gray.shape[1]}x{gray.shape[0]}"
                                   f" px but its header says {size[0]}x{size[1]}")
        det = detect_board(gray, board, detector=detector, max_side=max_side,
                           subpix_win=subpix_win, subpix_iters=subpix_iters,
                           subpix_eps=subpix_eps)
        v = ViewResult(name=names[i])
        if det is None:
            v.reason = ("board not found" if not board.charuco else
                        "board not found (fewer than 6 ChArUco corners)")
        else:
            v.status, v.detection = "used", det
        if keep_images:
            v.thumbnail = _thumb(gray)
        return v

    views: list[Optional[ViewResult]] = [None] * n
    done = 0
    if threads == 1:
        for i in range(n):
            views[i] = work(i)
            done += 1
            if progress:
                progress(done, n, names[i])
    else:
        with ThreadPoolExecutor(max_workers=threads) as pool:
            futs = {pool.submit(work, i): i for i in range(n)}
            try:
                for f in as_completed(futs):
                    i = futs[f]
                    views[i] = f.result()
                    done += 1
                    if progress:
                        progress(done, n, names[i])
            except BaseException:
                for f in futs:
                    f.cancel()
                raise
    return [v for v in views if v is not None], size


def _run_cv(views: list[ViewResult], board: Board, size: tuple[int, int], flags: int,
            non_planar: bool, criteria: Optional[tuple]) -> dict:
    import cv2

    obj_all = board.object_points()
    objs = [obj_all[v.detection.ids].reshape(-1, 1, 3) for v in views]
    imgs = [v.detection.corners.reshape(-1, 1, 2).astype(np.float32) for v in views]
    K0 = np.eye(3) if flags & cv2.CALIB_FIX_ASPECT_RATIO else None
    # OpenCV's default criteria; the release-object solver is slow (seconds) to reach
    # DBL_EPSILON, and 1e-10 changes nothing measurable.
    eps = 1e-10 if non_planar else np.finfo(float).eps
    crit = criteria or (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, eps)
    try:
        if non_planar:
            fixed = board.corner_grid[0] - 1
            (rms, K, dist, rvecs, tvecs, new_obj, std, _, _, pve) = cv2.calibrateCameraROExtended(
                objs, imgs, size, fixed, K0, None, flags=flags, criteria=crit)
            new_obj = np.asarray(new_obj, np.float64).reshape(-1, 3)
        else:
            (rms, K, dist, rvecs, tvecs, std, _, pve) = cv2.calibrateCameraExtended(
                objs, imgs, size, K0, None, flags=flags, criteria=crit)
            new_obj = None
    except cv2.error as exc:
        msg = str(exc).strip().splitlines()
        raise CalibrationError("OpenCV calibration failed: "
                               + (msg[-1] if msg else "unknown error")) from None
    if not (np.isfinite(rms) and np.all(np.isfinite(K)) and np.all(np.isfinite(dist))):
        raise CalibrationError("calibration diverged (non-finite result); check the board "
                               "size and the photos")
    return {"rms": float(rms), "K": np.asarray(K, np.float64), "dist": np.asarray(dist).ravel(),
            "rvecs": [np.asarray(r).ravel() for r in rvecs],
            "tvecs": [np.asarray(t).ravel() for t in tvecs],
            "std": np.asarray(std).ravel(), "per_view": np.asarray(pve).ravel(),
            "obj": new_obj}


def _names(views: Sequence[ViewResult], limit: int = 6) -> str:
    ns = [Path(v.name).name for v in views]
    if len(ns) > limit:
        return ", ".join(ns[:limit]) + f", ... ({len(ns)} in all)"
    return ", ".join(ns)


def calibrate_views(views: list[ViewResult], board: Board, image_size: tuple[int, int], *,
                    flags: int = 0, non_planar: bool = False, reject_outliers: bool = True,
                    outlier_factor: float = 3.0, outlier_min_px: float = 0.5,
                    max_rounds: int = 3, min_views: int = 3,
                    criteria: Optional[tuple] = None) -> CalibrationResult:
    """Calibrate from detections (views with ``status == "used"``), rejecting outliers.

    Parameters
    ----------
    views : list of ViewResult
        From :func:`detect_views`; updated in place (status, reason, errors, poses).
    board : Board
        The board.
    image_size : tuple of int
        ``(width, height)``.
    flags : int, optional
        ``cv2.CALIB_*`` flags (e.g. ``CALIB_FIX_ASPECT_RATIO``, ``CALIB_ZERO_TANGENT_DIST``,
        ``CALIB_RATIONAL_MODEL``).
    non_planar : bool, optional
        Use ``calibrateCameraROExtended`` (release-object method: also refines the board
        points, for boards that are not perfectly flat; full chessboard detections only).
    reject_outliers : bool, optional
        Drop views whose RMS error exceeds ``max(outlier_factor * median, outlier_min_px)``
        and calibrate again, up to ``max_rounds`` times, keeping at least ``min_views``.
    min_views : int, optional
        Fewest views with a board needed (3).
    criteria : tuple, optional
        Termination criteria of the optimisation (OpenCV's default when omitted).

    Returns
    -------
    CalibrationResult

    Raises
    ------
    CalibrationError
        Fewer than ``min_views`` views with a board, or OpenCV fails.
    """
    import cv2

    if min_views < 3:
        raise ValueError("min_views must be >= 3")
    found = [v for v in views if v.status == "used"]
    missing = [v for v in views if v.status != "used"]
    if len(found) < min_views:
        msg = (f"board ({board.describe()}) found in {len(found)} of {len(views)} images, "
               f"need at least {min_views}")
        if found:
            msg += f"; found in: {_names(found)}"
        if missing:
            msg += f"; not found in: {_names(missing)}"
        raise CalibrationError(msg + " (check --board: inner corners for a chessboard)")
    if non_planar and (board.charuco or any(len(v.detection.ids) != board.n_corners
                                             for v in found)):
        raise CalibrationError("the non-planar (release-object) calibration needs full "
                               "chessboard detections; use a chessboard, not ChArUco")
    t0 = time.perf_counter()
    active = list(found)
    for rnd in range(max_rounds + 1):
        res = _run_cv(active, board, image_size, flags, non_planar, criteria)
        errs = res["per_view"]
        if not reject_outliers:
            break
        med = float(np.median(errs))
        thr = max(outlier_factor * med, outlier_min_px)
        bad = sorted((i for i, e in enumerate(errs) if e > thr), key=lambda i: -errs[i])
        bad = bad[:max(0, len(active) - min_views)]
        if not bad or rnd == max_rounds:
            break
        for i in bad:
            v = active[i]
            v.status = "rejected"
            v.reason = (f"reprojection error {errs[i]:.2f} px > {thr:.2f} px "
                        f"({outlier_factor:g} x median {med:.2f} px)")
        drop = set(bad)
        active = [v for i, v in enumerate(active) if i not in drop]
    t_cal = time.perf_counter() - t0

    K, dist = res["K"], res["dist"]
    obj_all = board.object_points().astype(np.float64)
    if res["obj"] is not None:
        obj_all = res["obj"]
    for i, v in enumerate(active):
        v.rvec, v.tvec, v.error_px = res["rvecs"][i], res["tvecs"][i], float(errs[i])
    for v in views:
        if v.detection is None:
            continue
        obj = obj_all[v.detection.ids]
        img = v.detection.corners.astype(np.float64)
        if v.status == "rejected":  # pose the outlier with the final intrinsics, for the report
            ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist)
            if not ok:
                continue
            v.rvec, v.tvec = rvec.ravel(), tvec.ravel()
        proj, _ = cv2.projectPoints(obj, v.rvec, v.tvec, K, dist)
        v.residuals = proj.reshape(-1, 2) - img
        if v.status == "rejected":
            v.error_px = float(np.sqrt((v.residuals ** 2).sum(axis=1).mean()))
        v.coverage = view_parameters(v.detection, board, image_size)

    std_all = res["std"]
    std = {STD_NAMES[i]: float(std_all[i]) for i in range(min(4 + dist.size, len(std_all)))}
    cov = coverage_scores([v.coverage for v in active if v.coverage is not None])
    advice = coverage_advice(cov, len(active))
    rejected = [v for v in views if v.status == "rejected"]
    if len(rejected) > max(2, len(found) // 4):
        advice.append(f"{len(rejected)} views rejected as outliers: check for motion blur, "
                      f"a bent board or a wrong --square")
    if res["rms"] > 1.0:
        advice.append(f"RMS {res['rms']:.2f} px is high: use sharp, well-lit photos of a flat "
                      f"board; fixed focus (no autofocus change between shots)")
    extr = np.array([np.concatenate([v.rvec, v.tvec]) for v in active])
    info = CalibrationInfo(
        calibration_time=time.strftime("%c"), nframes=len(active),
        board_width=board.cols, board_height=board.rows, square_size=float(board.square_m),
        aspect_ratio=(float(K[0, 0] / K[1, 1]) if flags & cv2.CALIB_FIX_ASPECT_RATIO else None),
        flags=int(flags), avg_reprojection_error=res["rms"],
        per_view_reprojection_errors=errs, extrinsic_parameters=extr,
        std_deviations_intrinsics=std_all)
    camera = Camera(K, dist, image_size, info=info)
    return CalibrationResult(camera=camera, rms=res["rms"], views=views, std=std, coverage=cov,
                             advice=advice, board=board, timings={"calibrate": t_cal})


def calibrate(images: Sequence[Any], board: Board, *, names: Optional[Sequence[str]] = None,
              detector: str = "auto", max_side: int = 1000, subpix_win: Optional[int] = None,
              subpix_iters: int = 40, subpix_eps: float = 1e-3, flags: int = 0,
              non_planar: bool = False, reject_outliers: bool = True,
              outlier_factor: float = 3.0, outlier_min_px: float = 0.5, min_views: int = 3,
              threads: Optional[int] = None, criteria: Optional[tuple] = None,
              progress: Optional[Callable[[int, int, str], None]] = None,
              keep_images: bool = False) -> CalibrationResult:
    """Calibrate a camera from photos of a board.

    Parameters
    ----------
    images : sequence of path or numpy.ndarray
        Photos (files, or ``(H, W)`` gray / ``(H, W, 3)`` RGB uint8 arrays), all one size.
    board : Board
        Chessboard (inner corners) or ChArUco board (squares).
    names : sequence of str, optional
        Display names for the report.
    detector, max_side, subpix_win, subpix_iters, subpix_eps
        Detection settings, see :func:`~monodbh.calib.board.detect_board`.
    flags, non_planar, reject_outliers, outlier_factor, outlier_min_px, min_views, criteria
        Calibration settings, see :func:`calibrate_views`.
    threads : int, optional
        Detection threads (default ``min(4, cpu_count)``).
    progress : callable, optional
        ``progress(done, total, name)`` after each image is processed.
    keep_images : bool, optional
        Keep gray thumbnails in the views (for :func:`~monodbh.calib.debug.write_debug_overlays`).

    Returns
    -------
    CalibrationResult
        ``result.camera`` is ready for :func:`~monodbh.calib.save_camera`.

    Raises
    ------
    PhotoError
        An image cannot be read.
    CalibrationError
        Mixed image sizes, too few views with a board, or the optimisation fails.

    Examples
    --------
    >>> from monodbh.calib import Board, calibrate, save_camera
    >>> res = calibrate(sorted(Path("shots").glob("*.jpg")), Board(9, 6, 0.025))  # doctest: +SKIP
    >>> save_camera(res.camera, "cam.yaml")  # doctest: +SKIP
    """
    t0 = time.perf_counter()
    views, size = detect_views(images, board, names=names, detector=detector, max_side=max_side,
                               subpix_win=subpix_win, subpix_iters=subpix_iters,
                               subpix_eps=subpix_eps, threads=threads, progress=progress,
                               keep_images=keep_images)
    t_det = time.perf_counter() - t0
    res = calibrate_views(views, board, size, flags=flags, non_planar=non_planar,
                          reject_outliers=reject_outliers, outlier_factor=outlier_factor,
                          outlier_min_px=outlier_min_px, min_views=min_views, criteria=criteria)
    res.timings["detect"] = t_det
    return res
