"""The measuring pipeline: photo -> rope -> segmenter -> CDEN depth -> tree network -> DBH.

Imports only ``monodbh.calib``, the runtime predictors of ``monodbh.models`` (onnxruntime)
and this package; torch is loaded only through kornia, for the scene cloud.
"""
from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np

from ..calib.errors import MonodbhError
from .geometry import Perception, measure_from_perception
from .result import MeasureResult, PointCloud

__all__ = ["Session", "fresh_error_model", "measure_photo", "reconstruct_photo", "WORK_LONG_SIDE_PX", "DEPTH_FLIP_TTA", "unproject_depth",
           "rope_across_trunk", "ROPE_WEAK_SCORE"]

#: Photos are processed at this long side (pixels); edges are located to sub-pixel precision.
WORK_LONG_SIDE_PX = 1600
#: the stem-base network's probability needed to use its base. Measured on the calibration photos
#: (seeds 9100 + 9200, 118 measured; the shipped network): p >= 0.5 found 25 bases (scale error
#: median 1.9 %, 90th percentile 10.7 %), p >= 0.3 36 (2.4 %, 12.3 %); the 11 in 0.3-0.5 are
#: 5.5 % off on average where the depth network's distance is 20 % off
BASE_P_THRESHOLD = 0.3
#: with ``--rope-mm``, read the rope's thickness again on the full-resolution photo when it is
#: larger than the working image (see :func:`rope_at_full_resolution`)
ROPE_FULL_RES = True
#: the rope finder also checks a rope the band detector or the stem search found: where it sees
#: nothing at the chosen band, its own confident band replaces it, or the photo is refused
#: (``rope_finder.finder_check``)
ROPE_FINDER_CROSS_CHECK = True
#: the segmenter and the depth network run on a background thread while the band detector searches
#: for the rope (docs/decisions/threads.md)
OVERLAP_DEPTH = True
#: the depth network sees the photo and its mirror image (see :class:`~monodbh.models.runtime_gan.DepthPredictor`)
DEPTH_FLIP_TTA = True


class Session:
    """Loaded ONNX predictors, reused across photos.

    Parameters
    ----------
    models_dir : folder with ``manifest.json`` and the ``*.onnx`` files (default: the shipped
        models inside the package).
    threads : onnxruntime intra-op threads per model.
    """

    def __init__(self, models_dir: str | Path | None = None, threads: int = 2):
        from ..models.runtime import Segmenter, load_manifest
        from ..models.runtime_gan import DepthPredictor, TreePredictor
        t0 = time.perf_counter()
        mdir = Path(models_dir) if models_dir else Path(__file__).resolve().parent.parent / "models"
        if not (mdir / "manifest.json").exists():
            # editable installs keep models/ at the repository root
            import monodbh.models as _m
            mdir = Path(_m.__file__).resolve().parent
        manifest = load_manifest(mdir / "manifest.json")
        models = manifest.get("models", manifest)

        def path_of(kind):
            ent = models.get(kind)
            if not ent:
                raise MonodbhError(f"{mdir / 'manifest.json'}: no shipped '{kind}' model "
                                   f"(train it with 'dbh train' and 'dbh export RUN_DIR --ship')")
            p = mdir / ent["file"]
            if not p.exists():
                raise MonodbhError(f"{p}: model file missing")
            return p
        self.segmenter = Segmenter(path_of("segmenter"), threads=threads, manifest=manifest)
        self.depth = DepthPredictor(str(path_of("cden")), threads=threads, flip_tta=DEPTH_FLIP_TTA)
        self.trees = TreePredictor(str(path_of("treenet")), threads=threads)
        # the stem-base network is optional (without it the edge tracker looks for the base)
        self.base = None
        if models.get("basenet") and (mdir / models["basenet"]["file"]).exists():
            from ..models.runtime_base import BaseFinder
            self.base = BaseFinder(mdir / models["basenet"]["file"], threads=threads, manifest=manifest,
                                   threshold=BASE_P_THRESHOLD)
        # ... and so is the rope verifier (without it the stem search's logistic score decides)
        self.rope_verifier = None
        if models.get("ropenet") and (mdir / models["ropenet"]["file"]).exists():
            from ..models.runtime_rope import RopeVerifier
            self.rope_verifier = RopeVerifier(mdir / models["ropenet"]["file"], threads=threads, manifest=manifest)
        # ... and the mask-free rope finder (run only where the other two find no rope)
        self.rope_finder = None
        if models.get("ropeseg") and (mdir / models["ropeseg"]["file"]).exists():
            from ..models.runtime_ropeseg import RopeFinder
            self.rope_finder = RopeFinder(mdir / models["ropeseg"]["file"], threads=threads, manifest=manifest)
        self.models_dir = mdir
        # the error model measured for exactly these networks (python -m monodbh.toolkit.error_model
        # FOLDER --write): per-source 1-sigma; stale (built-in defaults, flagged) after retraining
        em = fresh_error_model(manifest)
        self.sigma_network = em.get("sigma")
        self.rank_network = em.get("rank")
        self.distance_calibration = em.get("distance_calibration")
        self.error_model_stale = bool(manifest.get("error_model")) and not em
        self._pool = None
        self.load_ms = 1000 * (time.perf_counter() - t0)

    def background(self, fn, *args) -> "_Job":
        """Run ``fn(*args)`` on the session's one background thread; ``.result()`` waits for it
        (and re-raises its exception). With :data:`OVERLAP_DEPTH` off the call runs at
        ``.result()``."""
        if not OVERLAP_DEPTH:
            return _Job(None, fn, args)
        if self._pool is None:
            from concurrent.futures import ThreadPoolExecutor
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="monodbh-depth")
        return _Job(self._pool.submit(fn, *args))


class _Job:
    """A background call's handle: a future, or (``fut`` None) a call deferred to :meth:`result`
    when the overlap is off."""

    def __init__(self, fut, fn=None, args=()):
        self._fut, self._fn, self._args = fut, fn, args
        self._done, self._value = False, None

    def result(self):
        if self._fut is not None:
            return self._fut.result()
        if not self._done:
            self._value, self._done = self._fn(*self._args), True
        return self._value

    def wait(self) -> None:
        """Block until a background call has finished (its exception, if any, is not raised)."""
        if self._fut is not None:
            from concurrent.futures import wait
            wait([self._fut])


#: the shipped networks the measured error model depends on (those shipped; basenet is optional;
#: the rope verifier and the rope finder only decide which photos are measured, not how well, so
#: they are not among them)
ERROR_MODEL_KINDS = ("segmenter", "cden", "treenet", "basenet")


def fresh_error_model(manifest: dict) -> dict:
    """``manifest["error_model"]`` when it was measured for exactly the shipped networks (their
    sha256) run as now (:data:`DEPTH_FLIP_TTA`), else ``{}`` (stale after retraining, or never
    measured)."""
    em = manifest.get("error_model") or {}
    models = manifest.get("models", manifest)
    shipped = {k: (models.get(k) or {}).get("sha256") for k in ERROR_MODEL_KINDS if k in models}
    fresh = (em.get("sigma") is not None and em.get("models") == shipped
             and bool(em.get("depth_flip_tta", False)) == DEPTH_FLIP_TTA)
    return em if fresh else {}


def _work_image(rgb: np.ndarray, camera):
    """Downscale to :data:`WORK_LONG_SIDE_PX` and undistort; returns (image, pinhole camera, scale)."""
    import cv2

    from ..calib import Camera
    H, W = rgb.shape[:2]
    s = min(1.0, WORK_LONG_SIDE_PX / max(W, H))
    w, h = int(round(W * s)), int(round(H * s))
    img = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA) if s < 1 else rgb
    cam = camera.for_image(W, H)
    # same physical camera at the working resolution (exact scale per axis)
    K = cam.K.copy()
    sx, sy = w / W, h / H
    K[0, 0] *= sx
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K[1, 1] *= sy
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    cw = Camera(K, cam.dist, (w, h), pose=cam.pose)
    if np.any(np.asarray(cam.dist) != 0):
        und, K_new = cw.undistort_image(img, alpha=0.0)
        pin = Camera(K_new, np.zeros(5), (w, h), pose=cam.pose)
        return und, pin, (sx, sy), cw
    return img, cw, (sx, sy), cw


def _full_res_crop(rgb: np.ndarray, camera, cam_work, scale, box) -> np.ndarray:
    """The undistorted full-resolution photo inside ``box`` = (x0, y0, x1, y1) (integers), given
    in the full-resolution pinhole frame of the working camera ``cam_work`` (its ``K`` scaled
    back up by 1 / ``scale``): (y1 - y0, x1 - x0, 3) uint8."""
    import cv2

    sx, sy = scale
    K = np.asarray(cam_work.K, np.float64).copy()
    K[0, 0] /= sx
    K[0, 2] = (K[0, 2] + 0.5) / sx - 0.5
    K[1, 1] /= sy
    K[1, 2] = (K[1, 2] + 0.5) / sy - 0.5
    H, W = rgb.shape[:2]
    x0, y0, x1, y1 = box
    cam = camera.for_image(W, H)
    if not np.any(np.asarray(cam.dist) != 0) and np.allclose(K, cam.K):
        xa, ya, xb, yb = max(x0, 0), max(y0, 0), min(x1, W), min(y1, H)
        out = np.zeros((y1 - y0, x1 - x0, 3), np.uint8)
        out[ya - y0:yb - y0, xa - x0:xb - x0] = rgb[ya:yb, xa:xb]
        return out
    u, v = np.meshgrid(np.arange(x0, x1, dtype=np.float64), np.arange(y0, y1, dtype=np.float64))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
    src, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), np.asarray(cam.K, np.float64),
                               np.asarray(cam.dist, np.float64))
    src = src.reshape(y1 - y0, x1 - x0, 2).astype(np.float32)
    return cv2.remap(rgb, src[..., 0], src[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def rope_at_full_resolution(rgb: np.ndarray, camera, cam_work, scale, rope) -> dict | None:
    """The rope's thickness read again on the full-resolution photo (a 12 MP photo is measured
    at :data:`WORK_LONG_SIDE_PX`, where a rope is 2.5x thinner than the sensor sees it).

    The rope band found in the working image is cut out of the undistorted full-resolution
    photo (with rows above and below it and part of the background beside it), the band
    detector is run again there at the same place, and its thickness and mean-profile contrast
    are returned in full-resolution pixels: ``{"thickness_px", "contrast", "scale"}`` with
    ``scale`` the working / full-resolution pixel ratio; None when the photo is no larger than
    the working image or the band is not found again at the same place.
    """
    from .rope import detect_rope, rope_profile_fwhm

    sx, sy = scale
    if max(sx, sy) > 0.95 or not rope or rope.polyline is None or len(rope.polyline) < 2:
        return None
    P = (np.asarray(rope.polyline, np.float64) + 0.5) / (sx, sy) - 0.5
    T = float(rope.thickness_px) / sx
    L = float(np.linalg.norm(P[-1] - P[0]))
    mx, my = 0.35 * L + 4 * T + 8, max(10 * T, 0.25 * L, 24.0)
    box = tuple(int(round(v)) for v in (P[:, 0].min() - mx, P[:, 1].min() - my,
                                        P[:, 0].max() + mx, P[:, 1].max() + my))
    crop = _full_res_crop(rgb, camera, cam_work, scale, box)
    c = (np.asarray(rope.center_xy, np.float64) + 0.5) / (sx, sy) - 0.5 - (box[0], box[1])
    det = detect_rope(crop, None, pick_xy=(float(c[0]), float(c[1])), min_score=-np.inf)
    if not det or np.hypot(*(np.asarray(det.center_xy) - c)) > max(3 * T, 0.15 * L) + 4:
        return None
    if not 0.4 < det.thickness_px / max(T, 1e-6) < 2.5:
        return None
    contrast = rope_profile_fwhm(crop, det.polyline, det.thickness_px)[1]
    return {"thickness_px": float(det.thickness_px), "contrast": float(contrast), "scale": float(sx)}


def _to_work_pixel(xy, scale, cam_distorted, cam_work) -> np.ndarray:
    """A photo pixel ``(x, y)`` -> the working image's pixel ``(2,)`` (downscaled, undistorted)."""
    sx, sy = scale
    p = np.array([[(xy[0] + 0.5) * sx - 0.5, (xy[1] + 0.5) * sy - 0.5]], np.float64)
    if cam_distorted is cam_work or not np.any(np.asarray(cam_distorted.dist) != 0):
        return p[0]
    return cam_distorted.undistort_points(p, K_new=cam_work.K)[0]


def _to_photo_pixel(xy, scale, cam_distorted, cam_work) -> np.ndarray:
    """A working-image pixel ``(x, y)`` (downscaled, undistorted) -> the photo's own pixel ``(2,)``.

    The inverse of :func:`_to_work_pixel`: a point the pipeline reports (the rope's centre, a
    refused band) lands on the same place of the photo the user looks at, and ``--pick`` with
    those coordinates reaches it again.
    """
    sx, sy = scale
    p = np.asarray(xy, np.float64)
    if cam_distorted is not cam_work and np.any(np.asarray(cam_distorted.dist) != 0):
        n = cam_work.undistort_points(p[None], normalized=True)[0]       # cam_work is a pinhole
        p = cam_distorted.project(np.array([[n[0], n[1], 1.0]]))[0]
    return np.array([(p[0] + 0.5) / sx - 0.5, (p[1] + 0.5) / sy - 0.5])


def _polyline_span(polyline) -> float | None:
    """End-to-end length (pixels) of a rope centre line ``(N, 2)``; None when missing."""
    if polyline is None or len(polyline) < 2:
        return None
    p = np.asarray(polyline, np.float64)
    return float(np.linalg.norm(p[-1] - p[0]))


def _rope_band_mask(rope, shape: tuple[int, int], height_factor: float = 3.0) -> np.ndarray:
    """(H, W) bool: a band along the stem, as wide as the rope's extent, centred on the rope.

    Used as the roped stem's mask when the segmenter missed the stem; its height is
    ``height_factor`` times the rope's length (above and below).
    """
    H, W = shape
    pl = np.asarray(rope.polyline, np.float64)
    d = pl[-1] - pl[0]
    L = float(np.linalg.norm(d))
    u = d / max(L, 1e-6)
    a = np.array([-u[1], u[0]])
    c = np.asarray(rope.center_xy, np.float64)
    hh = height_factor * L
    quad = np.array([c - u * L / 2 - a * hh, c + u * L / 2 - a * hh, c + u * L / 2 + a * hh,
                     c - u * L / 2 + a * hh])
    m = np.zeros((H, W), np.uint8)
    cv2.fillConvexPoly(m, np.round(quad).astype(np.int32), 1)
    return m > 0


def _dist_to_band(rope, xy) -> float:
    """Pixels from ``xy`` to a found rope's centre line (its middle when it has none)."""
    p = rope.polyline if rope.polyline is not None and len(rope.polyline) else np.asarray([rope.center_xy])
    p = np.asarray(p, np.float64)
    return float(np.min(np.hypot(p[:, 0] - xy[0], p[:, 1] - xy[1])))


def _roped_instance(instance: np.ndarray, xy, radius: int = 6) -> int:
    H, W = instance.shape
    x, y = int(round(xy[0])), int(round(xy[1]))
    win = instance[max(0, y - radius):y + radius + 1, max(0, x - radius):x + radius + 1]
    ids = win[win > 0]
    if ids.size == 0:
        return 0
    return int(np.bincount(ids).argmax())


#: a rope candidate scoring between this and the detector's ``min_score`` (1.0) is accepted when
#: it lies across a trunk the segmenter found (:func:`rope_across_trunk`). Measured on the seed
#: 9100 calibration set (75 roped photos): the true rope is the best band in 63, above 1.0 in
#: 54; 8 bands in [0, 1): the trunk check accepted 4 (all true ropes) and refused 3 (1 true
#: rope). On the 24 real rope-free photos: 1 false band above 1.0; of 4 in [0, 1) it accepted 1.
ROPE_WEAK_SCORE = 0.0


def rope_across_trunk(rope, instance: np.ndarray, cell: float) -> bool:
    """Whether a rope band lies across a segmented tree instance and spans about its width.

    Parameters
    ----------
    rope : :class:`~.rope.RopeDetection` (``center_xy``, ``direction``, ``polyline``).
    instance : (H, W) int tree instance ids (0 = none), same pixels as the rope.
    cell : size of one segmenter mask cell in pixels (the masks' resolution).
    """
    tid = _roped_instance(instance, rope.center_xy, radius=max(6, int(round(cell))))
    if tid == 0:
        return False
    H, W = instance.shape
    c = np.asarray(rope.center_xy, np.float64)
    u = np.asarray(rope.direction, np.float64)
    u = u / max(np.linalg.norm(u), 1e-9)
    t = np.arange(-0.6 * W, 0.6 * W, 1.0)
    pts = c[None] + t[:, None] * u[None]
    xi, yi = np.round(pts[:, 0]).astype(int), np.round(pts[:, 1]).astype(int)
    ok = (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
    on = np.zeros(len(t), bool)
    on[ok] = instance[yi[ok], xi[ok]] == tid
    k0 = int(np.argmin(np.abs(t)))
    if not on[max(0, k0 - int(cell)):k0 + int(cell) + 1].any():
        return False
    # the run of instance pixels through the rope centre (gaps under one cell bridged)
    idx = np.nonzero(on)[0]
    k = idx[np.argmin(np.abs(idx - k0))]
    lo = hi = k
    while lo > 0 and on[max(0, lo - int(cell) - 1):lo].any():
        lo -= 1
    while hi < len(t) - 1 and on[hi + 1:hi + int(cell) + 2].any():
        hi += 1
    width = float(hi - lo + 1)
    pl = np.asarray(rope.polyline, np.float64)
    length = float(np.hypot(*np.diff(pl, axis=0).T).sum()) if len(pl) > 1 else 0.0
    return 0.4 * width <= length <= 2.0 * width + 2 * cell


def unproject_depth(depth: np.ndarray, K: np.ndarray, step: int = 1) -> np.ndarray:
    """Camera-frame points ``(H', W', 3)`` from a z-depth map with kornia.

    Parameters
    ----------
    depth : (H, W) float32 metres.
    K : (3, 3) pinhole intrinsics of the depth map.
    step : keep every ``step``-th pixel in each direction (intrinsics adjusted).
    """
    import torch
    from kornia.geometry.depth import depth_to_3d_v2
    d = depth[::step, ::step]
    Ks = K.astype(np.float64).copy()
    Ks[:2] /= step          # pixel i of the subsampled map is pixel i * step of the original
    with torch.inference_mode():
        pts = depth_to_3d_v2(torch.from_numpy(np.ascontiguousarray(d, np.float32))[None],
                             torch.from_numpy(Ks.astype(np.float32))[None])
    return pts[0].numpy()


def measure_photo(path: str, camera, *, pick_xy=None, want_cloud: bool = False, want_debug: bool = False,
                  session: Session | None = None, gt: dict | None = None, base_xy=None,
                  rope_diameter_m: float | None = None) -> MeasureResult:
    """Measure the DBH of the roped tree in one photo.

    Parameters
    ----------
    path : photo file.
    camera : :class:`monodbh.calib.Camera` from cam.yaml (adapted to the photo here).
    pick_xy : (x, y) photo pixel choosing among several roped trees.
    base_xy : (x, y) photo pixel where the roped stem meets the ground (its front, middle),
        tapped by the user (``dbh measure --base X,Y``): sets the scale by single-view
        metrology between the rope and the base, the most accurate source without a pose.
    rope_diameter_m : the rope's true diameter (metres; ``dbh measure --rope-mm``): where the rope
        is at least ``ROPE_RULER_MIN_PX`` thick in the photo, its thickness sets the scale.
    want_cloud : also build the scene and tree point clouds (``result.debug['scene_cloud']``,
        ``result.debug['tree_cloud']``).
    want_debug : keep arrays for the overlay in ``result.debug``.
    session : reuse loaded models (created on first use otherwise).
    gt : ground-truth sample (``dbh eval --gt-perception``): masks, depth and silhouette from
        the sample instead of the networks (the single-view floor).

    Returns
    -------
    MeasureResult (``error`` set for photos that cannot be measured; never raises for those).
    """
    from ..calib import load_photo
    tm = {}
    t0 = time.perf_counter()
    try:
        rgb = load_photo(path)
    except MonodbhError as e:
        return MeasureResult(photo=str(path), error=str(e))
    tm["load"] = 1000 * (time.perf_counter() - t0)
    try:
        if gt is not None:
            return _measure_gt(path, rgb, camera, gt, tm)
        return _measure(path, rgb, camera, pick_xy, want_cloud, want_debug, session or Session(), tm,
                        base_xy=base_xy, rope_diameter_m=rope_diameter_m)
    except MonodbhError as e:
        return MeasureResult(photo=str(path), error=str(e), timings_ms=tm)


def _measure_gt(path, rgb, camera, gt, tm):
    from .gt import perception_from_ground_truth
    H, W = rgb.shape[:2]
    cam = camera.for_image(W, H)
    sample = dict(gt)
    sample["rgb"] = rgb
    perc = perception_from_ground_truth(sample, cam)
    if perc is None:
        return MeasureResult(photo=str(path), error=f"{path}: no rope found (ground truth has none)", timings_ms=tm)
    return measure_from_perception(perc, str(path), timings=tm)


def _measure(path, rgb, camera, pick_xy, want_cloud, want_debug, sess: Session, tm, base_xy=None,
             rope_diameter_m=None):
    t = time.perf_counter()
    img, cam, (sx, sy), cw = _work_image(rgb, camera)
    h, w = img.shape[:2]
    tm["undistort"] = 1000 * (time.perf_counter() - t)

    # the segmenter, then the depth network (it needs the trees' union), run on a background
    # thread while the band detector searches the whole photo for the rope (onnxruntime releases
    # the GIL; the band detector is mostly single-threaded numpy / OpenCV and needs no mask)
    fx = float(cam.K[0, 0])
    seg_job = sess.background(lambda: sess.segmenter.predict(img, size=(w, h)))
    depth_job = sess.background(lambda: sess.depth.predict(img, seg_job.result().instance > 0, fx))
    try:
        return _measure_rest(path, rgb, camera, pick_xy, want_cloud, want_debug, sess, tm, base_xy,
                             rope_diameter_m, img, cam, (sx, sy), cw, seg_job, depth_job)
    finally:
        # a refused photo still lets its networks finish (the next photo gets both cores)
        depth_job.wait()


def _measure_rest(path, rgb, camera, pick_xy, want_cloud, want_debug, sess, tm, base_xy, rope_diameter_m,
                  img, cam, scale, cw, seg_job, depth_job):
    from .rope import detect_rope
    sx, sy = scale
    h, w = img.shape[:2]

    # the segmenter's masks are coarse (one mask cell is ``cell`` photo pixels): the rope is
    # searched in the whole photo (measured on 38 roped bench photos: 28 found with no mask vs
    # 22 with the predicted tree mask, no wrong rope either way) and trunk edges are searched
    # up to half a cell away from the mask border
    out_shape = sess.segmenter.spec["outputs"][1]["shape"]
    cell = max(w / out_shape[-1], h / out_shape[-2])
    t = time.perf_counter()
    # a tap is a photo pixel: into the working image through the lens distortion, as --base
    pick = None if pick_xy is None else tuple(float(v) for v in _to_work_pixel(pick_xy, (sx, sy), cw, cam))
    rope = detect_rope(img, None, pick_xy=pick, weak_score=ROPE_WEAK_SCORE)
    # (the time waited for the segmenter here; it ran beside the band detector)
    t_seg = time.perf_counter()
    seg = seg_job.result()
    tm["segment"] = 1000 * (time.perf_counter() - t_seg)
    if not rope and rope.ambiguous and pick is None:
        # two bands score alike: when exactly one of the leading ones lies across a segmented
        # trunk, that one is the rope (the other is e.g. red paint, tape or clothing)
        top = [c for c in rope.candidates if c.score >= rope.candidates[0].score - 1.0][:4]
        on = [c for c in top if rope_across_trunk(c, seg.instance, cell)]
        if len(on) == 1:
            rope = detect_rope(img, None, pick_xy=on[0].center_xy)
        else:
            # ... or when exactly one of them sits on a stem with a rope-like red row there
            from .rope_stem import stem_evidence_choice
            k = stem_evidence_choice(img, seg.instance, [c.center_xy for c in top], rope_candidates=rope.candidates)
            if k is not None:
                rope = detect_rope(img, None, pick_xy=top[k].center_xy)
    weak_refused = bool(rope) and rope.weak and not rope_across_trunk(rope, seg.instance, cell)
    rope_flags = []
    pick_missed = False
    # at a user's tap, the band detector's nearest candidate is kept when it is near the tap and
    # rope-like; else the rope is searched on the tapped stem
    # (near: the tap within 15 px or two mask cells of the band's centre line, which on a near stem
    # runs far from its middle)
    off_pick = (pick is not None and bool(rope) and _dist_to_band(rope, pick) > max(15.0, 2 * cell))
    if ((not rope and not rope.ambiguous) or weak_refused
            or (pick is not None and (not rope or off_pick or rope.score < ROPE_WEAK_SCORE))):
        # a rope thinner than a pixel is no connected line: its red-ness averaged across the
        # segmented trunk's width still stands out (mask-guided search, toolkit/rope_stem.py)
        from .rope_stem import detect_rope_on_stems
        alt = detect_rope_on_stems(img, seg.instance, pick_xy=pick, rope_candidates=rope.candidates,
                                   verifier=sess.rope_verifier)
        if alt:
            rope, weak_refused = alt, False
            rope_flags.append("rope_from_stem_profile")
            if sess.rope_verifier is not None and pick is None:
                rope_flags.append("rope_verified_by_network")
        elif off_pick:
            # the nearest band is elsewhere: not what the user tapped (unless the finder sees it)
            pick_missed = True
    no_rope = not rope and not rope.ambiguous
    if sess.rope_finder is not None and (pick_missed or no_rope or (pick is None and weak_refused)):
        # neither the band detector nor the mask-guided stem search: the mask-free rope finder
        # (the segmenter may have missed or split the roped stem); at a tap, its candidate there
        from .rope_finder import rope_from_finder
        t_f = time.perf_counter()
        alt = rope_from_finder(sess.rope_finder.components(img), (h, w), pick_xy=pick)
        tm["rope_finder"] = 1000 * (time.perf_counter() - t_f)
        if alt or (alt.ambiguous and pick is None):
            rope, weak_refused, pick_missed = alt, False, False
            if alt:
                rope_flags.append("rope_found_by_network")
    elif (ROPE_FINDER_CROSS_CHECK and sess.rope_finder is not None and pick is None and rope
          and not weak_refused):
        # the band detector or the stem search found a rope: the finder checks it (a red band of
        # tape or leaves taken where the real rope was faint to the band detector)
        from .rope_finder import finder_check
        t_f = time.perf_counter()
        # one tile around the band (about 20 ms) tells support; the whole photo only without it
        verdict, alt = finder_check(rope, sess.rope_finder.components_near(img, rope.center_xy), (h, w),
                                    whole=lambda: sess.rope_finder.components(img))
        tm["rope_finder"] = 1000 * (time.perf_counter() - t_f)
        if verdict == "replaced":
            rope, rope_flags = alt, ["rope_found_by_network", "rope_chosen_by_network"]
        elif verdict == "unsupported":
            x, y = _to_photo_pixel(rope.center_xy, (sx, sy), cw, cam)
            raise MonodbhError(f"{path}: no red rope found (the red band at ({x:.0f},{y:.0f}) does not "
                               f"look like a rope to the rope finder; --pick X,Y to measure there)")
    elif (ROPE_FINDER_CROSS_CHECK and sess.rope_finder is not None and pick is not None and rope
          and not rope_flags):
        # at a tap the band detector's band may lie up to two mask cells off (a band beside the
        # rope's end); where the finder marks a band right at the tap, that is what was tapped
        from .rope_finder import FINDER_PICK_RADIUS_PX, FINDER_SUPPORT_MIN_PEAK, finder_support, rope_from_finder
        if _dist_to_band(rope, pick) > FINDER_PICK_RADIUS_PX:
            t_f = time.perf_counter()
            comps = sess.rope_finder.components_near(img, pick)
            if finder_support(comps, rope.center_xy) < FINDER_SUPPORT_MIN_PEAK:
                alt = rope_from_finder(comps, (h, w), pick_xy=pick)
                if alt:
                    rope, rope_flags = alt, ["rope_found_by_network"]
            tm["rope_finder"] = 1000 * (time.perf_counter() - t_f)
    if pick_missed:
        px, py = pick_xy
        raise MonodbhError(f"{path}: no red rope found at the picked point ({px:.0f},{py:.0f})")
    tm["rope"] = 1000 * (time.perf_counter() - t) - tm["segment"]
    if weak_refused:
        x, y = _to_photo_pixel(rope.center_xy, (sx, sy), cw, cam)
        raise MonodbhError(f"{path}: no red rope found (a faint red band at ({x:.0f},{y:.0f}) does not "
                           f"lie across a segmented trunk; --pick X,Y to measure there)")
    if not rope:
        # the detectors name places in working-image pixels: the user sees (and taps) the photo's
        import re
        reason = re.sub(r"\((-?\d+),(-?\d+)\)", lambda g: "({:.0f},{:.0f})".format(
            *_to_photo_pixel((float(g[1]), float(g[2])), (sx, sy), cw, cam)), rope.reason)
        raise MonodbhError(f"{path}: {reason}")
    tid = _roped_instance(seg.instance, rope.center_xy, radius=max(6, int(round(cell))))
    if tid == 0:
        # the segmenter missed the roped stem: the rope band spans the visible trunk, so a
        # band along the stem as wide as the rope stands in for its mask
        tree_mask = _rope_band_mask(rope, (h, w))
        flags_extra = ["tree_mask_from_rope"] + rope_flags
    else:
        # the rope spans the visible trunk: its band fills in stem the coarse mask missed
        # (e.g. the shaded half of a trunk)
        tree_mask = seg.instance == tid
        flags_extra = list(rope_flags)
    band_mask = _rope_band_mask(rope, (h, w), height_factor=1.0)
    rope_contrast = None
    rope_T = None if rope_flags else float(rope.thickness_px)
    rope_T_native = rope_T
    if rope_diameter_m and not rope_flags:
        full = None
        if ROPE_FULL_RES:
            # a photo larger than the working image: its thickness read where the sensor has
            # all its pixels (a rope too thin to measure at 1600 px may not be at 4000)
            t_f = time.perf_counter()
            full = rope_at_full_resolution(rgb, camera, cam, (sx, sy), rope)
            tm["rope_full_res"] = 1000 * (time.perf_counter() - t_f)
        if full is not None:
            rope_T, rope_T_native = full["thickness_px"] * full["scale"], full["thickness_px"]
            rope_contrast = full["contrast"]
            flags_extra.append("rope_read_at_full_resolution")
        else:
            # the rope as a ruler: how clearly its mean profile stands out (faint ropes read too thick)
            from .rope import rope_profile_fwhm
            rope_contrast = rope_profile_fwhm(img, rope.polyline, rope.thickness_px)[1]
    edge_mask = tree_mask | band_mask
    ground = seg.semantic == 1

    # (the depth map is waited for inside the geometry, after the steps that do not need it)

    tree_out = {}

    def silhouette_fn(z_axis, edges):
        t1 = time.perf_counter()
        center = 0.5 * (edges.left_xy + edges.right_xy)
        R_n, G_n, box = sess.trees.predict(img, tree_mask, tuple(center), edges.width_px, float(cam.K[0, 0]))
        zf, zb = sess.trees.to_metric(R_n, G_n, z_axis, box, float(cam.K[0, 0]), np.asarray(cam.K, float))
        P = zf.shape[0]
        s = box[2] / P
        M = np.array([[s, 0, box[0] + 0.5 * s], [0, s, box[1] + 0.5 * s]], np.float64)
        z1 = cv2.warpAffine(zf.astype(np.float32), M, (w, h), flags=cv2.INTER_LINEAR)
        z2 = cv2.warpAffine(zb.astype(np.float32), M, (w, h), flags=cv2.INTER_LINEAR)
        inside = cv2.warpAffine(np.ones((P, P), np.float32), M, (w, h), flags=cv2.INTER_NEAREST) > 0.5
        z1[~inside] = 0
        z2[~inside] = 0
        tree_out.update(z1=z1, z2=z2, box=box)
        tm["trees"] = 1000 * (time.perf_counter() - t1)
        return z1, z2

    perc = Perception(rgb=img, camera=cam, rope_xy=np.asarray(rope.center_xy, float),
                      rope_dir=np.asarray(rope.direction, float), rope_half_px=max(0.5, rope.thickness_px / 2),
                      tree_mask=tree_mask, ground_mask=ground, depth_job=depth_job, depth_is_metric=False,
                      silhouette_fn=silhouette_fn, source="network",
                      base_finder=None if sess.base is None else sess.base.find,
                      edge_search_px=max(3.0, 0.5 * cell), edge_mask=edge_mask,
                      sigma_network=sess.sigma_network, rank_network=sess.rank_network,
                      distance_calibration=sess.distance_calibration,
                      base_xy=None if base_xy is None else _to_work_pixel(base_xy, (sx, sy), cw, cam),
                      # (the finder's band is the rope's own extent across the stem: it checks the width)
                      rope_length_px=(None if rope_flags and "rope_found_by_network" not in rope_flags
                                      else _polyline_span(rope.polyline)),
                      rope_band_mask=band_mask,
                      # (a rope found on the stem profile is thinner than a pixel: no ruler)
                      rope_thickness_px=rope_T, rope_thickness_native_px=rope_T_native,
                      rope_contrast=rope_contrast,
                      rope_diameter_m=rope_diameter_m,
                      extra={"tree_mask_from_rope": tid == 0})
    res = measure_from_perception(perc, str(path), timings=tm)
    if sess.sigma_network is None:
        flags_extra.append("sigma_model_default")     # no error model measured for these networks
    res.flags = list(res.flags or []) + flags_extra
    res.tree_id = int(tid)
    if res.rope_xy is not None:
        res.debug["rope_xy"] = np.asarray(res.rope_xy, np.float64)      # working-image pixels (the overlay's)
        res.rope_xy = [float(v) for v in _to_photo_pixel(res.rope_xy, (sx, sy), cw, cam)]
    if res.error:
        res.error = f"{path}: {res.error}"
        return res
    if want_cloud or want_debug:
        t = time.perf_counter()
        cands = res.debug.get("scale_candidates", {})
        lam_net = cands.get("network", (None,))[0]
        lam = float(np.linalg.norm(res.debug["axis_point"]))
        s = lam / lam_net if lam_net else 1.0
        res.debug["scene_cloud"] = _scene_cloud(img, depth_job.result() * s, cam.K, seg.instance, tid)
        if tree_out:
            res.debug["tree_cloud"] = _tree_cloud(img, cam, tree_out, tree_mask, tid)
        tm["cloud"] = 1000 * (time.perf_counter() - t)
    if want_debug:
        res.debug.update(image=img, image_scale=(sx, sy), rope_polyline=np.asarray(rope.polyline),
                         tree_mask=tree_mask, rope_thickness_px=rope_T, rope_thickness_native_px=rope_T_native,
                         rope_contrast=rope_contrast, rope_flags=list(rope_flags))
    # the geometry step's own time (it called the tree network and the vanishing point)
    for k in ("depth", "vanishing", "geometry"):
        if k in res.timings_ms:
            tm[k] = res.timings_ms[k]
    if "geometry" in tm:
        tm["geometry"] = max(0.0, tm["geometry"] - tm.get("trees", 0.0) - tm.get("vanishing", 0.0)
                             - tm.get("depth", 0.0))
    res.timings_ms = tm
    res.timings_ms["total"] = sum(v for k, v in tm.items() if k != "total")
    return res


def _scene_cloud(img, depth, K, instance, tid, step: int = 4, max_depth_m: float = 60.0) -> PointCloud:
    pts = unproject_depth(depth, K, step)
    col = img[::step, ::step]
    ids = instance[::step, ::step].astype(np.int32)
    ok = (depth[::step, ::step] > 0) & (depth[::step, ::step] < max_depth_m)
    # the measured tree gets its refined cloud; keep its coarse points under id 0 out
    ok &= ids != tid
    return PointCloud(pts[ok].astype(np.float32), col[ok].astype(np.uint8), ids[ok])


def _tree_cloud(img, cam, tree_out, tree_mask, tid) -> PointCloud:
    z1, z2 = tree_out["z1"], tree_out["z2"]
    ys, xs = np.nonzero(tree_mask & (z1 > 0))
    if len(xs) == 0:
        return PointCloud.concat([])
    nxy = cam.undistort_points(np.c_[xs, ys].astype(np.float64), normalized=True)
    f = np.c_[nxy * z1[ys, xs, None], z1[ys, xs]]
    b = np.c_[nxy * z2[ys, xs, None], z2[ys, xs]]
    col = img[ys, xs]
    back_col = (col * 0.6).astype(np.uint8)
    return PointCloud(np.concatenate([f, b]).astype(np.float32), np.concatenate([col, back_col]),
                      np.full(2 * len(xs), tid, np.int32))


def reconstruct_photo(path: str, camera, session: Session | None = None, pick_xy=None, base_xy=None,
                      rope_diameter_m=None):
    """Measure and return ``(MeasureResult, PointCloud)``: the coarse scene cloud (metres,
    camera frame, rescaled by the rope) plus the refined cloud of the roped tree.
    ``base_xy``: the stem base pixel the user tapped (see :func:`measure_photo`)."""
    res = measure_photo(path, camera, pick_xy=pick_xy, want_cloud=True, session=session, base_xy=base_xy,
                        rope_diameter_m=rope_diameter_m)
    if res.error:
        return res, None
    cloud = PointCloud.concat([res.debug.get("scene_cloud"), res.debug.get("tree_cloud")])
    return res, cloud
