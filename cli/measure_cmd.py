"""``dbh measure``: DBH of the roped tree in one or many photos.

Top-level imports stay light (typer only); numpy, OpenCV, the pipeline and rich are imported
inside the command so ``dbh --help`` starts fast.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import List, Optional

import typer

__all__ = ["retake_hint", "measure", "parse_pick", "parse_tag_pattern", "load_calib", "fail", "check_outputs",
           "make_backend",
           "measure_fn_option",
           "session_factory_option"]


def parse_pick(text: Optional[str], option: str = "--pick") -> Optional[tuple[float, float]]:
    """``"1520,980"`` -> (1520.0, 980.0); None -> None.

    Raises
    ------
    typer.BadParameter
        Not two finite, non-negative numbers separated by a comma.
    """
    if text is None:
        return None
    parts = text.replace(" ", "").split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        x, y = float(parts[0]), float(parts[1])
    except ValueError:
        raise typer.BadParameter(f"expected X,Y pixel coordinates, got {text!r}", param_hint=option)
    if not (math.isfinite(x) and math.isfinite(y)) or x < 0 or y < 0:
        raise typer.BadParameter(f"pixel coordinates must be finite and >= 0, got {text!r}",
                                 param_hint=option)
    return x, y


def parse_tag_pattern(text: Optional[str]) -> Optional[str]:
    """``--tag-from`` checked: a regular expression Python compiles, or None.

    Raises
    ------
    typer.BadParameter
        Not a valid regular expression.
    """
    import re

    if text is None:
        return None
    try:
        re.compile(text)
    except re.error as exc:
        raise typer.BadParameter(f"not a regular expression ({exc})", param_hint="--tag-from")
    return text


def fail(message: str, code: int = 1) -> "typer.Exit":
    """Print ``error: message`` on stderr (one line; non-UTF-8 bytes of file names escaped) and
    return the Exit to raise."""
    from monodbh.toolkit.outputs.paths import printable

    typer.echo(f"error: {' '.join(printable(message).split())}", err=True)
    return typer.Exit(code)


def check_outputs(inputs, named=(), out_dir=None, planned=()) -> None:
    """Refuse outputs that are inputs, before anything is opened (exit 2): an output file the user
    named (``named``: ``(option, path)`` pairs such as ``("--csv", path)``) that is one of
    ``inputs`` (photos, camera file), or a file ``--out-dir`` would write (``planned``) that is.

    Raises
    ------
    typer.Exit
        After printing the one-line error.
    """
    from monodbh.toolkit.outputs.paths import check_not_input, first_clash, printable

    from monodbh.calib import MonodbhError

    try:
        for option, path in named:
            if path is not None:
                check_not_input(path, inputs, f"{option} {path}")
        clash = first_clash(planned, inputs) if out_dir is not None else None
    except MonodbhError as exc:
        raise fail(str(exc), 2)
    if clash:
        raise fail(f"--out-dir {printable(out_dir)} would overwrite the input {printable(clash[1])} "
                   f"(as {printable(Path(clash[0]).name)}); choose another folder", 2)


def load_calib(path: Path):
    """The camera of ``--calib`` (exit 1 with ``error: ...`` when it cannot be read)."""
    from monodbh.calib import MonodbhError, load_camera

    try:
        return load_camera(path)
    except MonodbhError as exc:
        raise fail(str(exc))


# Options shared by the measuring commands: which function/session to run. Hidden in
# measure/reconstruct/eval (tests inject a fake function here); shown by ``dbh bench``.
def measure_fn_option(hidden: bool = True, what: str = "measure_photo"):
    return typer.Option(None, "--measure-fn", hidden=hidden, metavar="MODULE:FUNCTION",
                        help=f"Function to run instead of the pipeline's {what}.", show_default=False)


def session_factory_option(hidden: bool = True):
    return typer.Option(None, "--session-factory", hidden=hidden, metavar="MODULE:FACTORY",
                        help="Session factory called as factory(models_dir=...) ('none': no session; "
                             "default: the function module's Session, else the pipeline's).",
                        show_default=False)


def make_backend(measure_fn: Optional[str], session_factory: Optional[str], models_dir: Optional[Path],
                 default_fn: Optional[str] = None):
    from monodbh.toolkit.batch import DEFAULT_MEASURE, DEFAULT_SESSION, Backend

    session = DEFAULT_SESSION if session_factory is None else session_factory
    if session.lower() in ("", "none"):
        session = None
    elif session_factory is None and measure_fn:
        # a custom function brings its own module's Session when it has one
        mod = measure_fn.partition(":")[0]
        session = f"{mod}:Session" if _has_attr(mod, "Session") else None
    return Backend(measure=measure_fn or default_fn or DEFAULT_MEASURE, session=session,
                   models_dir=str(models_dir) if models_dir else None)


def _has_attr(module: str, attr: str) -> bool:
    import importlib

    try:
        return hasattr(importlib.import_module(module), attr)
    except ImportError:
        return False


def _table(results, console, marker_known: bool = False) -> None:
    from rich.table import Table
    from rich.text import Text

    from monodbh.toolkit.outputs.overlay import format_dbh

    t = Table(show_header=True, header_style="bold", expand=False)
    # on a narrow terminal the long columns wrap instead of collapsing to nothing
    t.add_column("photo", overflow="fold", min_width=10)
    t.add_column("DBH", justify="right", no_wrap=True)
    t.add_column("distance", justify="right", no_wrap=True)
    t.add_column("scale", overflow="fold", min_width=10)
    t.add_column("flags / error", overflow="fold", min_width=12)
    t.add_column("time", justify="right", no_wrap=True, min_width=6)
    from monodbh.toolkit.outputs.paths import printable

    for r in results:
        total = (r.timings_ms or {}).get("total")
        tm = f"{total / 1000:.2f} s" if total is not None else ""
        if r.error:
            t.add_row(printable(r.photo), Text("-", style="red"), "", "", Text(printable(r.error), style="red"), tm)
        else:
            t.add_row(printable(r.photo), Text(format_dbh(r.dbh_cm, r.dbh_sigma_cm), style="bold"),
                      f"{r.distance_m:.2f} m" if r.distance_m is not None else "-",
                      r.scale_source or "-", Text(", ".join(r.flags), style="yellow"), tm)
    console.print(t)
    weak = [r for r in results if not r.error and not any(s in (r.scale_source or "")
                                                           for s in ("stem_base", "pose", "rope_diameter"))]
    if weak:
        console.print(Text(retake_hint(len(weak), len(results), marker_known), style="dim"))


def retake_hint(n_weak: int, n: int, marker_known: bool) -> str:
    """What to tell the user when ``n_weak`` of ``n`` photos took their scale from the depth network."""
    head = (f"{n_weak} of {n} measured with the scale from the depth network{_network_error_text()}, "
            "neither the stem's foot nor the marker could set it. To measure them better, retake: ")
    if marker_known:
        how = ("step back until the stem's foot is in the photo, or closer so that the marker is at "
               "least 5 px thick")
    else:
        how = ("step back until the stem's foot is in the photo, or give the marker's width "
               "(once: dbh marker CAM --width-mm W; or --rope-mm W)")
    return head + how + ". Where the foot is in the photo but was not found, tap it: --base X,Y"


def _network_error_text() -> str:
    """`` (about N % off, median)`` from the shipped error model's calibrated distances, or ``""``."""
    try:
        from monodbh.models.runtime import MANIFEST_PATH, fresh_error_model, load_manifest
        from monodbh.toolkit.config import MeasureConfig
        dc = fresh_error_model(load_manifest(MANIFEST_PATH), MeasureConfig().depth_mirror_average).get("distance_calibration") or {}
        m = float(dc["median_abs_ln_after"])
    except Exception:          # no manifest, no error model: the advice stands without a figure
        return ""
    return f" (about {100 * (math.exp(m) - 1):.0f} % off, median)"


def measure(
    photos: List[str] = typer.Argument(..., help="Photos (or folders of photos) of roped trees.",
                                       show_default=False),
    calib: Path = typer.Option(..., "--calib", "-c", help="Camera file (cam.yaml from dbh calibrate).",
                               show_default=False),
    as_json: bool = typer.Option(False, "--json", help="One JSON object per photo per line on stdout."),
    csv_out: Optional[Path] = typer.Option(None, "--csv", help="Also write a CSV (a row per photo, "
                                           "written as each photo finishes).", show_default=False),
    out_dir: Optional[Path] = typer.Option(None, "--out-dir", "-o", help="Write <stem>_overlay.png, "
                                           "<stem>_tree.ply, results.jsonl and summary.json here.",
                                           show_default=False),
    workers: int = typer.Option(1, "--workers", "-j", min=1, help="Processes measuring in parallel "
                                "(each loads the models once)."),
    pick: Optional[str] = typer.Option(None, "--pick", metavar="X,Y", help="Pixel on the rope (its knot "
                                       "or a hanging end will do): chooses among several roped trees, or "
                                       "finds a rope too faint to be found unasked (a tap where there is "
                                       "no rope is an error).", show_default=False),
    base: Optional[str] = typer.Option(None, "--base", metavar="X,Y", help="Pixel where the roped stem "
                                       "meets the ground (front, middle), one photo only: sets the "
                                       "scale from the rope-to-base geometry (about 10x more accurate "
                                       "than the depth network).", show_default=False),
    rope_mm: Optional[float] = typer.Option(None, "--rope-mm", min=1.0, max=100.0, help="The marker's true "
                                            "width in mm (rope diameter), for this run: overrides the "
                                            "camera file's marker_width_mm (set once with dbh marker). "
                                            "Where the marker is at least 5 px thick in the photo, it sets "
                                            "the scale.", show_default=False),
    resume: bool = typer.Option(False, "--resume", help="Keep the rows already in --csv (a run that "
                                "was stopped or killed) and measure only the photos not in it."),
    models_dir: Optional[Path] = typer.Option(None, "--models-dir", help="Folder of the ONNX models "
                                              "(default: the shipped ones).", show_default=False),
    geojson: Optional[Path] = typer.Option(None, "--geojson", help="Also write the trees' positions "
                                           "(from the photos' GPS, compass heading and the measured "
                                           "distance) as GeoJSON points with the rows' fields.",
                                           show_default=False),
    report: Optional[Path] = typer.Option(None, "--report", help="Also write an HTML report (one "
                                          "self-contained file: a sortable table with each photo's "
                                          "overlay, the DBH histogram, a map of the trees, the stand "
                                          "summary), at the end of the batch.", show_default=False),
    plot_area_m2: Optional[float] = typer.Option(None, "--plot-area-m2",
                                                 help="The plot's horizontal area, m^2: per-hectare "
                                                 "figures in the --report.", show_default=False),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", metavar="ADDRESS", help="Run the batch "
                                            "on the Dask cluster whose scheduler is at ADDRESS (e.g. "
                                            "tcp://10.0.0.5:8786; pip install monodbh[cluster]). Photos, "
                                            "camera file and --out-dir must be on a file system the "
                                            "workers share.", show_default=False),
    tag_from: Optional[str] = typer.Option(None, "--tag-from", metavar="REGEX", help="The row's tag: the "
                                           "first group (or the match) of REGEX in the file name "
                                           "(default and no match: the file stem).", show_default=False),
    measure_fn: Optional[str] = measure_fn_option(),
    session_factory: Optional[str] = session_factory_option(),
) -> None:
    """Measure the DBH of the roped tree in each photo.

    Exit status: 0 when every photo was measured, 1 when some failed (their rows carry the error; the others are still written), 2 on usage errors.
    """
    import sys

    pick_xy = parse_pick(pick)
    base_xy = parse_pick(base, "--base")
    if resume and csv_out is None:
        raise typer.BadParameter("--resume needs --csv (the results to resume)", param_hint="--resume")
    if plot_area_m2 is not None and not (math.isfinite(plot_area_m2) and plot_area_m2 > 0):
        raise typer.BadParameter(f"the plot's area must be a number of m^2 > 0, got {plot_area_m2:g}",
                                 param_hint="--plot-area-m2")
    if plot_area_m2 is not None and report is None:
        raise typer.BadParameter("--plot-area-m2 is for the --report (dbh summary takes it too)",
                                 param_hint="--plot-area-m2")
    if scheduler is not None and workers > 1:
        raise typer.BadParameter("the Dask cluster sets how many photos run at once; leave out --workers",
                                 param_hint="--scheduler")
    tag_pattern = parse_tag_pattern(tag_from)
    from monodbh.calib import MonodbhError
    from monodbh.toolkit.batch import Job, ResultWriter, expand_photos, unique_stems

    camera = load_calib(calib)
    paths = expand_photos(photos)
    if not paths:
        raise fail("no photos found in " + ", ".join(photos), 2)
    if base_xy is not None and len(paths) != 1:
        raise fail(f"--base is a pixel of one photo, but {len(paths)} photos were given", 2)
    stems = unique_stems(paths)
    from monodbh.toolkit.batch import output_files
    planned = ([] if out_dir is None else [out_dir / "results.jsonl", out_dir / "summary.json"]
               + [f for s in stems for f in output_files(out_dir, s)])
    check_outputs([*paths, calib], [("--csv", csv_out), ("--geojson", geojson), ("--report", report)],
                  out_dir, planned)
    _check_distinct([("--csv", csv_out), ("--geojson", geojson), ("--report", report)])
    from monodbh.toolkit.outputs.report import REPORT_THUMBNAIL_PX

    from .marker_cmd import marker_width_m
    rope_m, marker_from = marker_width_m(calib, rope_mm)
    jobs = [Job(i, p, camera, pick_xy=pick_xy, base_xy=base_xy, rope_diameter_m=rope_m,
                out_dir=str(out_dir) if out_dir else None,
                out_stem=s, tag_pattern=tag_pattern, thumbnail_px=REPORT_THUMBNAIL_PX if report else 0)
            for i, (p, s) in enumerate(zip(paths, stems))]
    backend = make_backend(measure_fn, session_factory, models_dir)

    from rich.console import Console

    err_console = Console(stderr=True, soft_wrap=True)
    try:
        writer = ResultWriter(json_stream=sys.stdout if as_json else None, csv_path=csv_out,
                              out_dir=out_dir, meta={"calib": str(calib), "workers": workers,
                                    "marker_width_mm": None if rope_m is None else round(rope_m * 1000, 3),
                                    "marker_width_from": marker_from}, resume=resume,
                              geojson_path=geojson, report_path=report,
                              report_options=_report_options(calib, rope_m, marker_from, plot_area_m2,
                                                             scheduler))
    except MonodbhError as exc:
        raise fail(str(exc))
    if writer.done:
        from monodbh.toolkit.outputs.paths import printable

        before = len(jobs)
        jobs = [j for j in jobs if printable(j.photo) not in writer.done]
        err_console.print(f"{before - len(jobs)} of {before} photos already in {printable(csv_out)}: "
                          f"kept (--resume)", highlight=False)
    n_photos = len(paths)
    interrupted = False
    with writer:
        try:
            _run(jobs, backend, workers, writer, err_console, scheduler)
        except KeyboardInterrupt:
            interrupted = True
        except MonodbhError as exc:  # the pipeline itself cannot start (models, import)
            try:
                writer.finish(interrupted=True)
            except MonodbhError:
                pass
            raise fail(str(exc))
        try:
            summary = writer.finish(interrupted=interrupted)
        except MonodbhError as exc:  # e.g. the GeoJSON cannot be written at the end
            raise fail(str(exc))
    if not as_json:
        _table(writer.results, Console(), marker_known=rope_m is not None)
    n, bad = summary["photos"], summary["failed"]
    if interrupted:
        err_console.print(f"interrupted after {n} of {n_photos} photos", style="yellow")
        raise typer.Exit(130)
    if len(jobs) > 1 or bad:
        err_console.print(f"{n - bad} of {n} photos measured" + (f", {bad} failed" if bad else ""),
                          style="red" if bad else None, highlight=False)
    raise typer.Exit(1 if bad else 0)


def _check_distinct(named) -> None:
    """Exit 2 when two output options (``(option, path)`` pairs) name the same file."""
    import os

    from monodbh.toolkit.outputs.paths import printable, same_file

    given = [(o, p) for o, p in named if p is not None]
    for i, (o1, p1) in enumerate(given):
        for o2, p2 in given[:i]:
            if os.path.abspath(p1) == os.path.abspath(p2) or same_file(p1, p2):
                raise fail(f"{o1} {printable(p1)} is the {o2} file; choose another output", 2)


def _report_options(calib, rope_m, marker_from, plot_area_m2, scheduler) -> dict:
    """``render_report`` keywords: the header's lines, the plot area, whether the marker is known."""
    from monodbh.toolkit.outputs.paths import printable

    meta = {"camera file": printable(calib),
            "marker width": None if rope_m is None else f"{rope_m * 1000:g} mm ({marker_from})",
            "plot area": None if plot_area_m2 is None else f"{plot_area_m2:g} m²",
            "Dask scheduler": scheduler}
    return {"meta": meta, "plot_area_m2": plot_area_m2, "marker_known": rope_m is not None}


def _run(jobs, backend, workers, writer, err_console, scheduler=None) -> None:
    from monodbh.toolkit.batch import iter_results
    from monodbh.toolkit.outputs.paths import printable

    if len(jobs) == 1 and scheduler is None:
        for res in iter_results(jobs, backend, workers=1):
            writer.add(res)
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    with Progress(TextColumn("[progress.description]{task.description}"), BarColumn(),
                  MofNCompleteColumn(), TimeRemainingColumn(), console=err_console,
                  transient=True) as prog:
        task = prog.add_task("measuring", total=len(jobs))
        for res in iter_results(jobs, backend, workers=workers, scheduler=scheduler):
            writer.add(res)
            prog.update(task, advance=1, description=printable(Path(res.photo).name))
