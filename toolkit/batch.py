"""Batch measuring: run a measure function over many photos, robustly, serially or in processes.

The measure function is named by a ``"module:attribute"`` spec (default
:data:`DEFAULT_MEASURE`, the pipeline's ``measure_photo``) so worker processes can import it and
``dbh bench`` (``monodbh.toolkit.evaluation.speed_bench``) can time any function with the same
signature::

    measure(path: str, camera, *, pick_xy=None, want_cloud=False, want_debug=False,
            session=None[, base_xy=(x, y)][, rope_diameter_m=float]) -> MeasureResult

``session`` comes from the session factory spec (default :data:`DEFAULT_SESSION`, called as
``factory(models_dir=...)`` once per process); ``base_xy`` is passed only when the user gave
the stem base (``--base``), ``rope_diameter_m`` only when the user gave the rope's diameter
(``--rope-mm``).

Guarantees of :func:`run_job` / :func:`iter_results`: one :class:`MeasureResult` per photo, in
input order, never an exception for a bad photo: a :class:`~monodbh.calib.errors.MonodbhError`
becomes the row's ``error`` (its one-line message); any other exception becomes
``"<photo>: internal error in <module:function>: <ExcType>: <message>"`` (the innermost
function of monodbh it was raised in, :func:`stage_of`) and the batch goes on. ``KeyboardInterrupt`` propagates. A problem with the
function or session themselves (import error, models missing) is raised once as
:class:`BatchError`, since every photo would fail the same way.

:class:`ResultWriter` (:mod:`monodbh.toolkit.outputs.results_file`, re-exported here) writes
the rows as they come.
"""
from __future__ import annotations

import importlib
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Optional, Sequence

from monodbh.calib.errors import MonodbhError

from .outputs.results_file import ResultWriter, csv_row, json_default, summarise  # re-exported
from .result import MeasureResult

__all__ = ["Backend", "Job", "BatchError", "ResultWriter", "DEFAULT_MEASURE", "DEFAULT_SESSION",
           "DEFAULT_RECONSTRUCT", "PHOTO_EXTENSIONS", "load_object", "run_job", "iter_results",
           "error_result", "normalise_result", "fill_field_record", "expand_photos", "unique_stems", "csv_row", "output_files",
           "OUTPUT_SUFFIXES", "stage_of",
           "one_line", "summarise", "json_default"]

DEFAULT_MEASURE = "monodbh.toolkit.pipeline:measure_photo"
DEFAULT_RECONSTRUCT = "monodbh.toolkit.pipeline:reconstruct_photo"
DEFAULT_SESSION = "monodbh.toolkit.pipeline:Session"

#: File extensions picked up when a folder is given instead of photos.
PHOTO_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".webp", ".bmp", ".heic", ".heif")


class BatchError(MonodbhError):
    """The measure function or its session cannot be set up (fatal for the whole batch)."""


def one_line(text: Any, limit: int = 400) -> str:
    """Collapse whitespace/newlines so the message fits one line (cut at ``limit`` characters)."""
    s = " ".join(str(text).split())
    return s if len(s) <= limit else s[:limit - 3] + "..."


def load_object(spec: str) -> Any:
    """Import ``"package.module:attribute"`` (attribute may be dotted).

    Raises
    ------
    BatchError
        Malformed spec, module not importable, or attribute missing.
    """
    mod_name, sep, attr = str(spec).partition(":")
    if not sep or not mod_name or not attr:
        raise BatchError(f"{spec!r}: expected 'module:function'")
    try:
        obj = importlib.import_module(mod_name)
    except ImportError as exc:
        raise BatchError(f"cannot import {mod_name} for {spec} ({one_line(exc)})") from None
    try:
        for part in attr.split("."):
            obj = getattr(obj, part)
    except AttributeError:
        raise BatchError(f"{mod_name} has no attribute {attr!r}") from None
    return obj


@dataclass(frozen=True)
class Backend:
    """Which measure function and session factory to use (picklable, by name).

    Parameters
    ----------
    measure : str
        ``"module:function"`` of the measure (or reconstruct) function.
    session : str or None
        ``"module:factory"`` called as ``factory(models_dir=models_dir)``; None or ``""`` for
        no session (``session=None`` is passed).
    models_dir : str or None
        Passed to the session factory.
    session_optional : bool
        When the session cannot be created (e.g. no shipped models), pass ``session=None``
        instead of failing (``dbh eval --gt-perception`` needs no networks).
    """
    measure: str = DEFAULT_MEASURE
    session: Optional[str] = DEFAULT_SESSION
    models_dir: Optional[str] = None
    session_optional: bool = False

    def function(self) -> Callable[..., Any]:
        fn = load_object(self.measure)
        if not callable(fn):
            raise BatchError(f"{self.measure} is not callable")
        return fn

    def new_session(self) -> Any:
        """A new session, or None without a session factory.

        Raises
        ------
        BatchError
            The factory cannot be imported or fails unexpectedly (MonodbhErrors pass through).
        """
        if not self.session:
            return None
        try:
            factory = load_object(self.session)
            try:
                return factory(models_dir=self.models_dir)
            except MonodbhError:
                raise
            except Exception as exc:
                raise BatchError(f"cannot create the session ({type(exc).__name__}: "
                                 f"{one_line(exc)})") from None
        except MonodbhError:
            if self.session_optional:
                return None
            raise


@dataclass
class Job:
    """One photo to measure.

    Attributes
    ----------
    index : int
        Position in the batch (results come back in this order).
    photo : str
        Path as given by the user (copied into ``MeasureResult.photo``).
    camera : object
        Camera model (``monodbh.calib.Camera``), picklable.
    pick_xy : (float, float) or None
        Pixel the user clicked on the roped tree.
    base_xy : (float, float) or None
        Pixel the user tapped where the roped stem meets the ground (passed to the measure
        function as ``base_xy=`` only when given).
    rope_diameter_m : float or None
        The rope's true diameter (passed as ``rope_diameter_m=`` only when given).
    out_dir : str or None
        Write ``<out_stem>_overlay.png`` (and ``<out_stem>_tree.ply`` when the result has a
        ``debug['tree_cloud']``) there.
    out_stem : str or None
        File stem for the outputs (default: the photo's stem).
    want_cloud : bool
        Ask the pipeline for the tree's cloud (implied by ``out_dir``).
    tag_pattern : str or None
        Regular expression giving the row's ``tag`` from the file name
        (:func:`~.photo_meta.tag_of`); None: the file stem.
    thumbnail_px : int
        > 0: set ``MeasureResult.thumbnail_jpeg`` to the overlay downscaled to this longest
        side (for ``--report``; :func:`~.outputs.report.thumbnail_jpeg`); 0: none.
    """
    index: int
    photo: str
    camera: Any
    pick_xy: Optional[tuple[float, float]] = None
    base_xy: Optional[tuple[float, float]] = None
    rope_diameter_m: Optional[float] = None
    out_dir: Optional[str] = None
    out_stem: Optional[str] = None
    want_cloud: bool = False
    tag_pattern: Optional[str] = None
    thumbnail_px: int = 0


def error_result(photo: str, exc: BaseException | str) -> MeasureResult:
    """Row for a failed photo: ``error`` set, every measurement None."""
    if isinstance(exc, str):
        msg = exc
    elif isinstance(exc, MonodbhError):
        msg = str(exc) or type(exc).__name__
    else:
        stage = stage_of(exc)
        msg = (f"{photo}: internal error{f' in {stage}' if stage else ''}: "
               f"{type(exc).__name__}: {exc}")
    return MeasureResult(photo=str(photo), error=one_line(msg))


def stage_of(exc: BaseException) -> Optional[str]:
    """Where in monodbh ``exc`` was raised: ``"module:function"`` of the innermost frame of its
    traceback inside the package (e.g. ``"toolkit.rope.finder:knot_band"``), or None."""
    import traceback

    roots = _package_roots()
    for fs in reversed(traceback.extract_tb(exc.__traceback__)):
        try:
            f = Path(fs.filename).resolve()
        except (OSError, RuntimeError):
            continue
        for name, root in roots:
            if f.is_relative_to(root):
                mod = ".".join((name, *f.relative_to(root).with_suffix("").parts)).removesuffix(".__init__")
                if mod == "toolkit.batch":      # the harness: raised by a measure function outside
                    return None
                return f"{mod}:{fs.name}"
    return None


def _package_roots() -> list[tuple[str, Path]]:
    import monodbh.calib
    import monodbh.models
    import monodbh.toolkit

    return [(m.__name__.split(".", 1)[1], Path(m.__path__[0]).resolve())
            for m in (monodbh.toolkit, monodbh.models, monodbh.calib)]


def normalise_result(res: Any, photo: str) -> MeasureResult:
    """Enforce the record's contract on what a measure function returned.

    ``photo`` is the user's path; ``dbh_cm``/``dbh_sigma_cm`` are None exactly when ``error``
    is set; messages are one line; ``flags`` is a list of str.
    """
    if not isinstance(res, MeasureResult):
        return error_result(photo, f"{photo}: internal error: TypeError: measure function returned "
                                   f"{type(res).__name__}, not MeasureResult")
    res.photo = str(photo)
    res.flags = [str(f) for f in (res.flags or [])]
    res.timings_ms = dict(res.timings_ms or {})
    res.estimates_cm = dict(res.estimates_cm or {})
    if res.error:
        res.error = one_line(res.error)
        res.dbh_cm = res.dbh_sigma_cm = None
    else:
        res.error = None
        bad = res.dbh_cm is None or not math.isfinite(float(res.dbh_cm))
        if bad:
            keep = res.debug
            res = error_result(photo, f"{photo}: internal error: no DBH and no error (dbh_cm={res.dbh_cm!r})")
            res.debug = keep
    return res


#: the side outputs of a photo in ``--out-dir``: ``<stem>_overlay.png`` and ``<stem>_tree.ply``
OUTPUT_SUFFIXES = ("_overlay.png", "_tree.ply")


def output_files(out_dir: str | os.PathLike, stem: str) -> list[Path]:
    """The overlay and cloud paths of a photo with output ``stem`` in ``out_dir``, their names cut
    to fit the file system (:func:`~.outputs.paths.fit_name`)."""
    from .outputs.paths import fit_name

    return [Path(out_dir) / fit_name(stem, sfx) for sfx in OUTPUT_SUFFIXES]


def _write_outputs(job: Job, res: MeasureResult) -> None:
    """Overlay PNG and tree PLY of one photo (``job.out_dir``) and the overlay's thumbnail
    (``job.thumbnail_px``); failures become flags, never exceptions."""
    from .outputs.overlay import render_overlay, save_overlay

    rgb = None
    try:
        rgb = render_overlay(res)
    except MonodbhError:  # e.g. the photo itself cannot be read: nothing to draw on
        pass
    except Exception:
        res.flags.append("overlay_failed")
    if job.thumbnail_px and rgb is not None:
        from .outputs.report import thumbnail_jpeg

        try:
            res.thumbnail_jpeg = thumbnail_jpeg(rgb, job.thumbnail_px)
        except Exception:  # noqa: BLE001 - the report shows the row without a picture
            res.thumbnail_jpeg = None
    if not job.out_dir:
        return
    overlay_path, cloud_path = output_files(job.out_dir, job.out_stem or Path(job.photo).stem)
    if rgb is not None:
        try:
            save_overlay(overlay_path, rgb)
        except Exception:
            res.flags.append("overlay_failed")
    cloud = (res.debug or {}).get("tree_cloud")
    if cloud is not None and len(cloud):
        try:
            from .outputs.cloud_io import write_cloud

            write_cloud(cloud_path, cloud)
        except Exception:
            res.flags.append("cloud_write_failed")


def _check_photo_file(photo: str) -> None:
    """A :class:`~monodbh.calib.errors.PhotoError` unless ``photo`` is a regular file (a FIFO or a
    device would block or never end)."""
    from monodbh.calib.errors import PhotoError

    if os.path.isfile(photo):
        return
    if os.path.isdir(photo):
        raise PhotoError(f"{photo}: is a directory, not a photo")
    if os.path.exists(photo):
        raise PhotoError(f"{photo}: not a regular file (a pipe, socket or device)")
    if os.path.islink(photo):
        try:
            os.stat(photo)
        except OSError as exc:
            if exc.strerror and "symbolic links" in exc.strerror:
                raise PhotoError(f"{photo}: cannot read ({exc.strerror})") from None
    raise PhotoError(f"{photo}: no such file")


def run_job(job: Job, measure: Callable[..., Any], session: Any = None, *,
            keep_debug: bool = False) -> MeasureResult:
    """Measure one photo and write its side outputs; never raises for a bad photo.

    ``timings_ms['total']`` is set to the wall time of the measure call when the function did
    not report one. ``debug`` is dropped unless ``keep_debug``.
    """
    t0 = time.perf_counter()
    want_debug = bool(job.out_dir or job.thumbnail_px) or keep_debug
    try:
        _check_photo_file(job.photo)
        kw: dict[str, Any] = dict(pick_xy=job.pick_xy, want_cloud=bool(job.want_cloud or job.out_dir),
                                  want_debug=want_debug, session=session)
        if job.base_xy is not None:
            kw["base_xy"] = tuple(job.base_xy)
        if job.rope_diameter_m is not None:
            kw["rope_diameter_m"] = float(job.rope_diameter_m)
        res = normalise_result(measure(job.photo, job.camera, **kw), job.photo)
    except (KeyboardInterrupt, SystemExit):
        raise
    except Exception as exc:  # MonodbhError -> its message; others -> internal error
        res = error_result(job.photo, exc)
    res.timings_ms.setdefault("total", (time.perf_counter() - t0) * 1000.0)
    fill_field_record(res, job)
    if job.out_dir or job.thumbnail_px:
        _write_outputs(job, res)
    if not keep_debug:
        res.debug = {}
    return res


def fill_field_record(res: MeasureResult, job: Job) -> None:
    """Set the row's field record: ``tag``, the EXIF time, camera position and heading, and
    (measured rows) the stem's bearing and the tree's position. Never raises; what cannot be
    known stays None (:mod:`.photo_meta`, :func:`.outputs.geo.fill_geo`)."""
    from .photo_meta import read_photo_meta, tag_of

    try:
        res.tag = tag_of(job.photo, job.tag_pattern)
    except Exception:  # noqa: BLE001 - a pattern the CLI did not check
        res.tag = tag_of(job.photo)
    meta = read_photo_meta(job.photo)
    res.taken_at = meta.taken_at
    res.camera_lat_deg, res.camera_lon_deg, res.camera_alt_m = meta.lat_deg, meta.lon_deg, meta.alt_m
    res.gps_accuracy_m = meta.accuracy_m
    res.camera_heading_deg, res.camera_heading_ref = meta.heading_deg, meta.heading_ref
    res.stem_bearing_deg = res.tree_lat_deg = res.tree_lon_deg = None
    try:
        from .outputs.geo import fill_geo

        fill_geo(res, job.camera, meta.width, meta.height)
    except Exception:  # noqa: BLE001 - geodesy never fails a row
        res.stem_bearing_deg = res.tree_lat_deg = res.tree_lon_deg = None


# -- processes ---------------------------------------------------------------------------------
_WORKER: dict[str, Any] = {}


def _worker_init(backend: Backend) -> None:
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and cancels
    _WORKER.clear()
    try:
        _WORKER["fn"] = backend.function()
        _WORKER["session"] = backend.new_session()
    except Exception as exc:  # reported on the first job, raised in the parent
        _WORKER["fatal"] = (f"{exc}" if isinstance(exc, MonodbhError)
                            else f"{type(exc).__name__}: {one_line(exc)}")


def _worker_run(job: Job) -> MeasureResult | tuple[str, str]:
    if "fatal" in _WORKER:
        return ("fatal", _WORKER["fatal"])
    return run_job(job, _WORKER["fn"], _WORKER["session"])


def iter_results(jobs: Sequence[Job], backend: Backend, *, workers: int = 1,
                 keep_debug: bool = False, session: Any = None,
                 scheduler: Optional[str] = None) -> Iterator[MeasureResult]:
    """Measure ``jobs`` and yield their results in order, as soon as each is available.

    Parameters
    ----------
    jobs : sequence of Job
    backend : Backend
        Measure function and session factory.
    workers : int
        1: in this process (one session, created on first use unless ``session`` is given);
        N > 1: N spawned processes, each creating its own session once.
    keep_debug : bool
        Keep ``result.debug`` (serial mode only; worker results never carry it).
    session : object, optional
        Ready session for serial mode.
    scheduler : str, optional
        Address of a Dask scheduler (``tcp://host:8786``): the jobs run on its cluster, one
        session per worker process (:mod:`.cluster`; ``workers`` is ignored).

    Raises
    ------
    BatchError / MonodbhError
        The measure function or session cannot be set up.
    """
    jobs = list(jobs)
    if not jobs:
        return
    if scheduler is not None:
        from .cluster import iter_cluster_results

        yield from iter_cluster_results(jobs, backend, scheduler)
        return
    if workers <= 1 or len(jobs) == 1:
        fn = backend.function()
        if session is None:
            session = backend.new_session()
        for job in jobs:
            yield run_job(job, fn, session, keep_debug=keep_debug)
        return

    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor
    from concurrent.futures.process import BrokenProcessPool

    pool = ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=mp.get_context("spawn"),
                               initializer=_worker_init, initargs=(backend,))
    try:
        futures = [pool.submit(_worker_run, job) for job in jobs]
        for job, fut in zip(jobs, futures):
            try:
                res = fut.result()
            except BrokenProcessPool:
                res = error_result(job.photo, f"{job.photo}: internal error: BrokenProcessPool: a worker process "
                                              "died (out of memory?)")
            except Exception as exc:  # e.g. unpicklable result
                res = error_result(job.photo, exc)
            if isinstance(res, tuple):
                raise BatchError(res[1])
            yield res
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


# -- inputs --------------------------------------------------------------------------------------
def expand_photos(paths: Iterable[str]) -> list[str]:
    """Photos in the order given; a folder expands to its image files (sorted, not recursive).

    Missing paths are kept (they become error rows).
    """
    out: list[str] = []
    for p in paths:
        p = str(p)
        if os.path.isdir(p):
            out += sorted(str(q) for q in Path(p).iterdir()
                          if q.is_file() and q.suffix.lower() in PHOTO_EXTENSIONS)
        else:
            out.append(p)
    return out


def unique_stems(photos: Sequence[str]) -> list[str]:
    """Output file stems, unique within the batch (``IMG_1``, ``IMG_1_2``, ...)."""
    seen: dict[str, int] = {}
    out = []
    for p in photos:
        stem = Path(p).stem or "photo"
        n = seen.get(stem, 0) + 1
        seen[stem] = n
        out.append(stem if n == 1 else f"{stem}_{n}")
    return out
