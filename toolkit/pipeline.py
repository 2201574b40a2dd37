"""The measuring pipeline: photo -> rope -> networks -> geometry -> DBH, as named stages.

Lives here: :class:`Session` (the loaded networks and the configuration they measure with),
:func:`measure_photo` and :func:`reconstruct_photo`. Imported by ``monodbh.cli`` and users;
imports ``monodbh.calib``, the networks' runtime (``monodbh.models.runtime``, onnxruntime) and
the library's own modules; torch is loaded only through kornia, for the scene cloud.

Stages of :func:`measure_photo`: load the photo; its working image (:mod:`.frames`); the
segmenter and the depth network started on a background thread; the rope (:mod:`.rope.select`);
the roped stem's masks; the rope as a ruler (:mod:`.rope.ruler`); the geometry, which calls the
tree network and waits for the depth map where it needs them; the result in the photo's own
pixels, clouds and timings.
"""
from __future__ import annotations

import re
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..calib.errors import MonodbhError
from .config import MeasureConfig
from .frames import WorkFrame, read_photo, square_crop, work_frame
from .orientation import sideways_score
from .geometry import Perception, measure_from_perception
from .geometry.edges import band_mask
from .result import MeasureResult, PointCloud
from .rope.geometry import instance_in_window
from .rope.select import Refusal, RopeChoice, RopeSource, select_rope

__all__ = ["Session", "MeasureConfig", "measure_photo", "reconstruct_photo", "rope_band_mask"]


class Session:
    """Loaded ONNX predictors, reused across photos, and the configuration they measure with.

    Parameters
    ----------
    models_dir : folder with ``manifest.json`` and the ``*.onnx`` files (default: the shipped
        models inside the package).
    threads : onnxruntime intra-op threads per model.
    config : :class:`~monodbh.toolkit.config.MeasureConfig` (defaults when None).
    """

    def __init__(self, models_dir: str | Path | None = None, threads: int = 2,
                 config: MeasureConfig | None = None):
        from ..models.runtime import load_networks
        self.config = config or MeasureConfig()
        t0 = time.perf_counter()
        nets = load_networks(models_dir, threads=threads, depth_flip_tta=self.config.depth_mirror_average,
                             stem_base_threshold=self.config.stem_base_threshold, spin=self.config.ort_spin)
        self.segmenter = nets.segmenter
        self.depth = nets.depth
        self.trees = nets.tree
        # the optional networks: None when not shipped
        self.base = nets.stem_base
        self.edge = nets.stem_edge if self.config.edge_network else None
        self.rope_verifier = nets.rope_verifier
        self.rope_finder = nets.rope_finder
        self.models_dir = nets.models_dir
        # the error model measured for exactly these networks: per-source 1-sigma; stale
        # (built-in defaults, flagged) after retraining
        self.sigma_network = nets.sigma
        self.rank_network = nets.rank
        self.distance_calibration = nets.distance_calibration
        self.error_model_stale = nets.error_model_stale
        self._trunk_net, self._trunk_net_file = None, nets.trunk_net
        self._threads, self._spin = threads, self.config.ort_spin
        self._pool = None
        self.load_ms = 1000 * (time.perf_counter() - t0)

    @property
    def trunk_net(self):
        """The trunk network (:class:`~monodbh.models.runtime.trunk_net.TrunkNet`, loaded on
        first use), or None where none is shipped."""
        if self._trunk_net is None and self._trunk_net_file is not None:
            from ..models.runtime.trunk_net import TrunkNet
            self._trunk_net = TrunkNet(self._trunk_net_file, threads=self._threads, spin=self._spin)
        return self._trunk_net

    def background(self, fn, *args) -> "_Job":
        """Run ``fn(*args)`` on the session's one background thread; ``.result()`` waits for it
        (and re-raises its exception). With ``config.overlap_networks`` off the call runs at
        ``.result()``."""
        if not self.config.overlap_networks:
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


@dataclass(frozen=True)
class _Request:
    """What the user asked for one photo (taps in the photo's own pixels)."""
    pick_xy: tuple[float, float] | None = None
    base_xy: tuple[float, float] | None = None
    rope_diameter_m: float | None = None
    want_cloud: bool = False
    want_debug: bool = False


def measure_photo(path: str, camera, *, pick_xy=None, want_cloud: bool = False, want_debug: bool = False,
                  session: Session | None = None, base_xy=None,
                  rope_diameter_m: float | None = None) -> MeasureResult:
    """Measure the DBH of the roped tree in one photo.

    Parameters
    ----------
    path : photo file.
    camera : :class:`monodbh.calib.Camera` from cam.yaml (adapted to the photo here).
    pick_xy : (x, y) photo pixel choosing among several roped trees, or on a rope too faint to be
        found unasked (``dbh measure --pick X,Y``).
    base_xy : (x, y) photo pixel where the roped stem meets the ground (its front, middle),
        tapped by the user (``dbh measure --base X,Y``): sets the scale by single-view
        metrology between the rope and the base, the most accurate source without a pose.
    rope_diameter_m : the rope's true diameter (metres; ``dbh measure --rope-mm``): where the rope
        is thick enough in the photo, its thickness sets the scale.
    want_cloud : also build the scene and tree point clouds (``result.debug['scene_cloud']``,
        ``result.debug['tree_cloud']``).
    want_debug : keep arrays for the overlay in ``result.debug``.
    session : reuse loaded models and their configuration (created on first use otherwise).

    Returns
    -------
    MeasureResult (``error`` set for photos that cannot be measured; never raises for those).

    Examples
    --------
    >>> from monodbh.calib import load_camera
    >>> from monodbh.toolkit import measure_photo
    >>> res = measure_photo("toolkit/examples/example.jpg", load_camera("toolkit/examples/cam.yaml"))
    >>> res.error is None and 5 < res.dbh_cm < 60
    True
    """
    tm = {}
    t0 = time.perf_counter()
    try:
        rgb = read_photo(path)
    except MonodbhError as e:
        return MeasureResult(photo=str(path), error=str(e))
    tm["load"] = 1000 * (time.perf_counter() - t0)
    req = _Request(pick_xy, base_xy, rope_diameter_m, want_cloud, want_debug)
    try:
        _check_taps(path, rgb.shape, req)
        return _measure(path, rgb, camera, req, session or Session(), tm)
    except MonodbhError as e:
        msg = _naming(path, str(e))
        cfg = session.config if session is not None else MeasureConfig()
        if "no red rope found" in msg and sideways_score(rgb) < cfg.sideways_score_max:
            msg += ("; the photo may be on its side (turned 90 degrees with no EXIF orientation): "
                    "rotate it upright")
        return MeasureResult(photo=str(path), error=msg, timings_ms=tm)


def _naming(path, message: str) -> str:
    """``message`` starting with the photo's path (errors raised below it may not name it)."""
    return message if message.startswith(str(path)) else f"{path}: {message}"


def _check_taps(path, shape, req: _Request) -> None:
    """The user's taps (``--pick``, ``--base``) must fall inside the ``shape`` (H, W, ...) photo."""
    h, w = shape[:2]
    for option, xy in (("--pick", req.pick_xy), ("--base", req.base_xy)):
        if xy is None:
            continue
        x, y = (float(v) for v in xy)
        if not (np.isfinite(x) and np.isfinite(y) and -0.5 <= x <= w - 0.5 and -0.5 <= y <= h - 0.5):
            raise MonodbhError(f"{path}: {option} {x:g},{y:g} is outside the {w}x{h} px photo "
                               f"(pixels from 0,0 at the top left to {w - 1},{h - 1})")


def _measure(path, rgb, camera, req: _Request, sess: Session, tm: dict) -> MeasureResult:
    """The working image, then the networks started beside the rope search, then the rest."""
    t = time.perf_counter()
    frame = work_frame(rgb, camera, sess.config.work_long_side_px)
    tm["undistort"] = 1000 * (time.perf_counter() - t)
    seg_job, depth_job = _start_networks(sess, frame)
    try:
        return _measure_frame(path, rgb, camera, req, sess, tm, frame, seg_job, depth_job)
    finally:
        # a refused photo still lets its networks finish (the next photo gets both cores)
        depth_job.wait()


def _start_networks(sess: Session, frame: WorkFrame):
    """The segmenter, then the depth network (it needs the trees' union), on the background
    thread: onnxruntime releases the GIL, and the band detector needs no mask."""
    img = frame.image
    h, w = frame.shape
    fx = float(frame.camera.K[0, 0])
    seg_job = sess.background(lambda: sess.segmenter.predict(img, size=(w, h)))
    depth_job = sess.background(lambda: sess.depth.predict(img, seg_job.result().instance > 0, fx))
    return seg_job, depth_job


def _measure_frame(path, rgb, camera, req: _Request, sess: Session, tm: dict, frame: WorkFrame,
                   seg_job, depth_job) -> MeasureResult:
    """Rope, roped stem, ruler, geometry, result: the stages after the networks were started."""
    cell = _mask_cell(sess, frame)
    at_tap = _TapInstances(sess, frame, seg_job, req, cell)
    choice = _find_rope(path, frame, at_tap, cell, req, sess, tm)
    seg = seg_job.result()
    stem = _roped_stem(choice, at_tap(), frame.shape, cell)
    from .rope.ruler import rope_ruler
    ruler = rope_ruler(rgb, camera, frame, choice.rope, is_line=choice.source.is_line,
                       diameter_known=bool(req.rope_diameter_m),
                       full_resolution=sess.config.rope_full_resolution, edges=sess.config.marker_edges,
                       finder_band=choice.source is RopeSource.FINDER, timings=tm)
    silhouette = _TreeSilhouette(sess.trees, frame, stem.tree_mask, tm)
    perc = _perception(frame, choice, stem, ruler, seg.semantic == 1, depth_job, silhouette, sess, req)
    res = measure_from_perception(perc, str(path), timings=tm, config=sess.config.geometry)
    flags = stem.flags + choice.flags + ruler.flags
    if at_tap.added and stem.tid == int(at_tap().max()):
        flags.append("trunk_segmented_at_tap")  # the roped stem came from the second pass at the tap
    if sideways_score(frame.image) < sess.config.sideways_score_max:
        flags.append("photo_maybe_sideways")    # light from a side: turned 90 degrees without EXIF?
    if sess.sigma_network is None:
        flags.append("sigma_model_default")     # no error model measured for these networks
    res.flags = list(res.flags or []) + flags
    res.tree_id = int(stem.tid)
    if res.rope_xy is not None:
        res.debug["rope_xy"] = np.asarray(res.rope_xy, np.float64)      # working-image pixels (the overlay's)
        res.rope_xy = [float(v) for v in frame.to_photo(res.rope_xy)]
    if res.error:
        res.error = f"{path}: {res.error}"
        return res
    _check_plausible(res, path, frame, sess.config)
    _check_row_against_marker(res, path, frame, choice, req, sess.config.row_marker_max_px)
    if req.want_cloud or req.want_debug:
        _clouds(res, frame, at_tap(), stem, silhouette, depth_job, tm, lambda: _trunk_pixels(sess, frame, req))
    if req.want_debug:
        res.debug.update(image=frame.image, image_scale=frame.scale, rope_polyline=np.asarray(choice.rope.polyline),
                         tree_mask=stem.tree_mask, rope_thickness_px=ruler.thickness_px,
                         rope_thickness_native_px=ruler.thickness_native_px, rope_contrast=ruler.contrast,
                         rope_flags=choice.flags)
    res.timings_ms = _stage_times(tm, res.timings_ms)
    return res


def _check_plausible(res: MeasureResult, path, frame: WorkFrame, cfg: MeasureConfig) -> None:
    """Refuse a result no tree can give: a distance at which the widest marker
    (``cfg.max_marker_width_m``) would be under one photo pixel thick, where no rope can be seen,
    or a DBH over ``cfg.max_dbh_cm``. Such a result comes from a band or a stem base taken
    elsewhere (e.g. a base found a few pixels below a band near the horizon); raises
    :class:`MonodbhError`."""
    fx_photo = float(frame.camera.K[0, 0]) / float(frame.scale[0])
    far = res.distance_m is not None and res.distance_m > cfg.max_marker_width_m * fx_photo
    wide = res.dbh_cm is not None and res.dbh_cm > cfg.max_dbh_cm
    if far or wide:
        why = (f"a {1000 * cfg.max_marker_width_m:g} mm marker is under a pixel thick beyond "
               f"{cfg.max_marker_width_m * fx_photo:.0f} m" if far else f"over {cfg.max_dbh_cm:g} cm")
        at = "" if res.distance_m is None else f" at {res.distance_m:.0f} m"
        raise MonodbhError(f"{path}: implausible result (DBH {res.dbh_cm or 0:.0f} cm{at}: {why}): the rope or "
                           f"the stem base was taken elsewhere; --pick X,Y on the rope, --base X,Y on the "
                           f"stem's foot")


def _check_row_against_marker(res: MeasureResult, path, frame: WorkFrame, choice: RopeChoice, req: _Request,
                              max_px: float) -> None:
    """A rope found only as a faint red row across a trunk (the stem search) is thinner than a
    pixel or two; with the marker's width known, the marker at the measured distance would be
    ``t = fx w / Z`` working-image pixels thick. Where that is ``max_px`` or more, the band
    detector would have seen it as a line: the row is something else (a branch, reddish bark) and
    the photo is refused, or at a tap flagged ``row_thinner_than_marker`` (the user said it is the
    rope); raises :class:`MonodbhError` where refused."""
    if choice.source not in (RopeSource.STEM_PROFILE, RopeSource.STEM_VERIFIED) or not req.rope_diameter_m:
        return
    if not res.distance_m or max_px is None:
        return
    t = float(frame.camera.K[0, 0]) * req.rope_diameter_m / float(res.distance_m)
    if t < max_px:
        return
    if req.pick_xy is not None:
        res.flags = list(res.flags or []) + ["row_thinner_than_marker"]
        return
    x, y = frame.to_photo(choice.rope.center_xy)
    raise MonodbhError(f"{path}: no red rope found (the faint red row at ({x:.0f},{y:.0f}) is much thinner "
                       f"than the {1000 * req.rope_diameter_m:g} mm marker would be at {res.distance_m:.1f} m, "
                       f"{t:.0f} px; --pick X,Y on the marker to measure there)")


def _mask_cell(sess: Session, frame: WorkFrame) -> float:
    """One segmenter mask cell in working-image pixels: the masks are coarse, so the rope is
    searched in the whole photo and trunk edges up to half a cell away from the mask border."""
    h, w = frame.shape
    out_shape = sess.segmenter.spec["outputs"][1]["shape"]
    return max(w / out_shape[-1], h / out_shape[-2])


class _TapInstances:
    """The segmenter's (h, w) tree instances, as the rope cascade and the roped stem read them.

    A tap (``--pick``) that finds no rope may lie on a thin far trunk the segmenter missed at its
    256 x 256 input. Where no tree lies within a mask cell of the tap, :meth:`add_tree_at_tap`
    runs the segmenter again on a square crop round the tap (``MeasureConfig.edge_mask_zoom`` of
    the long side, as for the edge mask) and adds the tree it finds under the tap as a new
    instance where the whole photo's pass left background; the cascade is then run again
    (docs/decisions/taps.md)."""

    def __init__(self, sess: Session, frame: WorkFrame, seg_job, req: _Request, cell: float):
        self.sess, self.frame, self.seg_job, self.cell = sess, frame, seg_job, cell
        self.pick = None if req.pick_xy is None else tuple(float(v) for v in frame.to_work(req.pick_xy))
        self.instance = None
        self.added = False

    def __call__(self) -> np.ndarray:
        if self.instance is None:
            self.instance = self.seg_job.result().instance
        return self.instance

    def add_tree_at_tap(self) -> bool:
        """Add the tree a close-up finds under the tap (see above); whether one was added."""
        zoom, inst0 = self.sess.config.edge_mask_zoom, self()
        r = max(6, int(round(self.cell)))
        if self.added or self.pick is None or zoom is None or instance_in_window(inst0, self.pick, r):
            return False
        x0, y0, x1, y1 = square_crop(self.pick, zoom, self.frame.shape)
        crop = np.ascontiguousarray(self.frame.image[y0:y1, x0:x1])
        inst = self.sess.segmenter.predict(crop, size=(x1 - x0, y1 - y0)).instance
        tid = instance_in_window(inst, (self.pick[0] - x0, self.pick[1] - y0), r)
        if not tid:
            return False
        out = inst0.copy()
        region = out[y0:y1, x0:x1]
        region[(inst == tid) & (region == 0)] = int(out.max()) + 1
        self.instance, self.added = out, True
        return True


def _find_rope(path, frame: WorkFrame, at_tap: _TapInstances, cell: float, req: _Request, sess: Session,
               tm: dict) -> RopeChoice:
    """:func:`~.rope.select.select_rope` on the working image; a refusal raises the user's error,
    with the places it names in the photo's own pixels (the ones the user sees and taps)."""
    t = time.perf_counter()
    pick = at_tap.pick
    marker_mm = None if req.rope_diameter_m is None else 1000.0 * req.rope_diameter_m
    choice = select_rope(frame.image, at_tap, cell, pick_xy=pick, verifier=sess.rope_verifier,
                         finder=sess.rope_finder, config=sess.config.rope, marker_width_mm=marker_mm)
    if choice.refusal in (Refusal.PICK_MISSED, Refusal.NOT_FOUND) and at_tap.add_tree_at_tap():
        seg_wait = choice.timings_ms.get("segment", 0.0)
        choice = select_rope(frame.image, at_tap, cell, pick_xy=pick, verifier=sess.rope_verifier,
                             finder=sess.rope_finder, config=sess.config.rope, marker_width_mm=marker_mm)
        choice.timings_ms["segment"] = seg_wait + choice.timings_ms.get("segment", 0.0)
    tm.update(choice.timings_ms)
    tm["rope"] = 1000 * (time.perf_counter() - t) - tm["segment"]
    if choice:
        return choice
    if choice.refusal is Refusal.PICK_MISSED:
        px, py = req.pick_xy
        raise MonodbhError(f"{path}: no red rope found at the picked point ({px:.0f},{py:.0f})")
    if choice.refusal is Refusal.NOT_FOUND:
        reason = re.sub(r"\((-?\d+),(-?\d+)\)", lambda g: "({:.0f},{:.0f})".format(
            *frame.to_photo((float(g[1]), float(g[2])))), choice.rope.reason)
        raise MonodbhError(f"{path}: {reason}")
    x, y = frame.to_photo(choice.at_xy)
    if choice.refusal is Refusal.WEAK_OFF_TRUNK:
        raise MonodbhError(f"{path}: no red rope found (a faint red band at ({x:.0f},{y:.0f}) does not "
                           f"lie across a segmented trunk; --pick X,Y to measure there)")
    raise MonodbhError(f"{path}: no red rope found (the red band at ({x:.0f},{y:.0f}) does not "
                       f"look like a rope to the rope finder; --pick X,Y to measure there)")


@dataclass
class _Stem:
    """The roped stem's masks in the working image."""
    tid: int                    # its segmenter instance (0: the segmenter missed it)
    tree_mask: np.ndarray       # (h, w) bool
    band_mask: np.ndarray       # (h, w) bool band as wide as the rope's extent, one rope length high
    flags: list


def _roped_stem(choice: RopeChoice, instance: np.ndarray, shape, cell: float) -> _Stem:
    """The segmenter's instance under the rope; where it missed the stem, the rope band spans the
    visible trunk, so a band along the stem as wide as the rope stands in for its mask."""
    rope = choice.rope
    tid = instance_in_window(instance, rope.center_xy, max(6, int(round(cell))))
    if tid == 0:
        tree_mask, flags = rope_band_mask(rope, shape), ["tree_mask_from_rope"]
    else:
        tree_mask, flags = instance == tid, []
    return _Stem(tid, tree_mask, rope_band_mask(rope, shape, height_factor=1.0), flags)


def rope_band_mask(rope, shape: tuple[int, int], height_factor: float = 3.0) -> np.ndarray:
    """(H, W) bool: a band along the stem, as wide as the rope's extent, centred on the rope,
    ``height_factor`` times the rope's length above and below it.

    Parameters
    ----------
    rope : :class:`~.rope.detection.RopeDetection` (``polyline`` (N, 2), ``center_xy``).
    shape : (H, W) of the mask.
    """
    pl = np.asarray(rope.polyline, np.float64)
    d = pl[-1] - pl[0]
    L = float(np.linalg.norm(d))
    return band_mask(shape, rope.center_xy, d / max(L, 1e-6), -L / 2, L / 2, height_factor * L)


def _polyline_span(polyline) -> float | None:
    """End-to-end length (pixels) of a rope centre line ``(N, 2)``; None when missing."""
    if polyline is None or len(polyline) < 2:
        return None
    p = np.asarray(polyline, np.float64)
    return float(np.linalg.norm(p[-1] - p[0]))


class _TreeSilhouette:
    """The tree network's front and back surface of the roped stem, as the geometry asks for it
    (:attr:`~.geometry.Perception.silhouette_fn`): metric maps in the working image."""

    def __init__(self, trees, frame: WorkFrame, tree_mask: np.ndarray, timings: dict):
        self.trees, self.frame, self.tree_mask, self.timings = trees, frame, tree_mask, timings
        self.z1 = self.z2 = self.box = None

    def __call__(self, z_axis, edges):
        t1 = time.perf_counter()
        img, cam = self.frame.image, self.frame.camera
        h, w = self.frame.shape
        center = 0.5 * (edges.left_xy + edges.right_xy)
        R_n, G_n, box = self.trees.predict(img, self.tree_mask, tuple(center), edges.width_px, float(cam.K[0, 0]))
        zf, zb = self.trees.to_metric(R_n, G_n, z_axis, box, float(cam.K[0, 0]), np.asarray(cam.K, float))
        P = zf.shape[0]
        s = box[2] / P
        M = np.array([[s, 0, box[0] + 0.5 * s], [0, s, box[1] + 0.5 * s]], np.float64)
        z1 = cv2.warpAffine(zf.astype(np.float32), M, (w, h), flags=cv2.INTER_LINEAR)
        z2 = cv2.warpAffine(zb.astype(np.float32), M, (w, h), flags=cv2.INTER_LINEAR)
        inside = cv2.warpAffine(np.ones((P, P), np.float32), M, (w, h), flags=cv2.INTER_NEAREST) > 0.5
        z1[~inside] = 0
        z2[~inside] = 0
        self.z1, self.z2, self.box = z1, z2, box
        self.timings["trees"] = 1000 * (time.perf_counter() - t1)
        return z1, z2


def _zoomed_stem_mask(sess: Session, frame: WorkFrame, rope_xy, frac: float) -> np.ndarray | None:
    """(H, W) bool mask of the roped stem from a second segmenter pass on a square crop of side
    ``frac`` x the working image's long side centred on ``rope_xy`` (kept inside the image): the
    instance under most of the pixels within 3 px of the rope's centre; None where there is none.
    At the segmenter's 256 x 256 input the crop is seen 1/frac times finer than the whole photo
    (docs/decisions/zoomed-edge-mask.md)."""
    h, w = frame.shape
    x0, y0, x1, y1 = square_crop(rope_xy, frac, (h, w))
    inst = sess.segmenter.predict(np.ascontiguousarray(frame.image[y0:y1, x0:x1]), size=(x1 - x0, y1 - y0)).instance
    px, py = int(round(float(rope_xy[0]))) - x0, int(round(float(rope_xy[1]))) - y0
    win = inst[max(0, py - 3):max(0, py + 4), max(0, px - 3):max(0, px + 4)]
    ids = win[win > 0].astype(np.int64)
    if not ids.size:
        return None
    m = np.zeros((h, w), bool)
    m[y0:y1, x0:x1] = inst == int(np.bincount(ids).argmax())
    return m


def _perception(frame: WorkFrame, choice: RopeChoice, stem: _Stem, ruler, ground_mask, depth_job,
                silhouette: _TreeSilhouette, sess: Session, req: _Request) -> Perception:
    """Everything the geometry needs, in the working image."""
    rope = choice.rope
    cell = _mask_cell(sess, frame)
    emask = None
    if sess.config.edge_mask_zoom is not None:
        emask = _zoomed_stem_mask(sess, frame, rope.center_xy, sess.config.edge_mask_zoom)
    if emask is None:
        emask = stem.tree_mask
    return Perception(
        rgb=frame.image, camera=frame.camera, rope_xy=np.asarray(rope.center_xy, float),
        rope_dir=np.asarray(rope.direction, float), rope_half_px=max(0.5, rope.thickness_px / 2),
        tree_mask=stem.tree_mask, ground_mask=ground_mask, depth_job=depth_job, depth_is_metric=False,
        silhouette_fn=silhouette, source="network",
        base_finder=None if sess.base is None else sess.base.find,
        edge_finder=None if sess.edge is None else sess.edge.find,
        edge_search_px=max(3.0, 0.5 * cell), edge_mask=emask | stem.band_mask,
        sigma_network=sess.sigma_network, rank_network=sess.rank_network,
        distance_calibration=sess.distance_calibration,
        base_xy=None if req.base_xy is None else frame.to_work(req.base_xy),
        # the band detector's and the finder's bands are the rope's own extent across the stem:
        # they check the stem's width (a stem-search row is not)
        rope_length_px=_polyline_span(rope.polyline) if choice.source.spans_stem else None,
        rope_polyline=None if rope.polyline is None else np.asarray(rope.polyline, np.float64),
        rope_band_mask=stem.band_mask,
        rope_thickness_px=ruler.thickness_px, rope_thickness_native_px=ruler.thickness_native_px,
        rope_contrast=ruler.contrast, rope_thickness_edges=ruler.edges, rope_diameter_m=req.rope_diameter_m,
        extra={"tree_mask_from_rope": stem.tid == 0})


def _trunk_pixels(sess: Session, frame: WorkFrame, req: _Request):
    """The working image's trunk pixels (H, W) bool for the clouds, from the trunk network in
    tiles (:meth:`~monodbh.models.runtime.trunk_net.TrunkNet.trunk_map`), else the segmenter's
    trunk head (:meth:`~monodbh.models.runtime.segmenter.Segmenter.trunk_map`); None where no
    cloud is asked for or neither is shipped."""
    if not req.want_cloud:
        return None
    if sess.trunk_net is not None:
        return sess.trunk_net.trunk_map(frame.image) >= sess.trunk_net.threshold
    seg = sess.segmenter
    if not getattr(seg, "has_trunk", False):
        return None
    return seg.trunk_map(frame.image) >= seg.trunk_threshold


def _clouds(res: MeasureResult, frame: WorkFrame, instance, stem: _Stem, silhouette: _TreeSilhouette,
            depth_job, tm: dict, trunk=None) -> None:
    """The scene cloud (the depth map rescaled to the measured distance) and the tree's cloud;
    ``trunk``: a function giving the trunk pixels (H, W) bool that flag their points, or None."""
    from .clouds import scene_cloud, tree_cloud
    t = time.perf_counter()
    trunk = trunk() if trunk is not None else None
    cands = res.debug.get("scale_candidates", {})
    lam_net = cands.get("network", (None,))[0]
    lam = float(np.linalg.norm(res.debug["axis_point"]))
    s = lam / lam_net if lam_net else 1.0
    res.debug["scene_cloud"] = scene_cloud(frame.image, depth_job.result() * s, frame.camera.K, instance,
                                           stem.tid, trunk=trunk)
    if silhouette.z1 is not None:
        res.debug["tree_cloud"] = tree_cloud(frame.image, frame.camera, silhouette.z1, silhouette.z2,
                                             stem.tree_mask, stem.tid, trunk=trunk)
    tm["cloud"] = 1000 * (time.perf_counter() - t)


def _stage_times(tm: dict, geometry_tm: dict) -> dict:
    """Per-stage times (ms): the geometry's own time without the tree network, the vanishing point
    and the wait for the depth map it called, plus the total."""
    for k in ("depth", "vanishing", "geometry"):
        if k in geometry_tm:
            tm[k] = geometry_tm[k]
    if "geometry" in tm:
        tm["geometry"] = max(0.0, tm["geometry"] - tm.get("trees", 0.0) - tm.get("vanishing", 0.0)
                             - tm.get("depth", 0.0))
    tm["total"] = sum(v for k, v in tm.items() if k != "total")
    return tm


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
