"""``dbh bench``: start-up, per-stage latency and memory of a measure function, in a fresh process.

:func:`run_bench` starts ``python -c`` :data:`BENCH_CHILD_CODE` (so start-up counts the
interpreter and every import), whose :func:`bench_child` creates the session and measures the
photo ``warmup + repeat`` times through ``toolkit.batch.run_job``; :func:`bench_report` turns its
record into the numbers checked against :data:`BENCH_TARGETS`, :func:`print_bench` prints them.
:func:`synth_camera_file` writes the camera of a ``dbh synth`` photo for ``--calib``.

Imported by ``monodbh.cli.eval_cmd`` and run by the benchmark process; imports
``toolkit.batch`` and :mod:`.synth_eval` (rich only to print).
"""
from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

from monodbh.calib.errors import MonodbhError
from monodbh.toolkit.batch import Backend, Job, json_default, one_line, run_job

__all__ = ["BENCH_TARGETS", "BENCH_MARK", "BENCH_CHILD_CODE", "BenchError", "run_bench", "bench_child",
           "bench_report", "print_bench", "synth_camera_file"]

#: Acceptance targets of ``dbh bench``: seconds per (12 MP) photo after start-up, start-up
#: seconds, peak memory MiB (1.5 GiB).
BENCH_TARGETS = {"per_photo_s": 1.0, "startup_s": 2.0, "peak_mib": 1536.0}


class BenchError(MonodbhError):
    """The benchmark process cannot run, finish or measure (its one-line reason)."""


def synth_camera_file(photo: str | Path, folder: str | Path) -> Path:
    """``folder/cam.yaml``: the camera of a ``dbh synth`` photo, from the ``.json`` beside it.

    Raises
    ------
    BenchError
        No readable ``dbh synth`` camera beside the photo.
    """
    from monodbh.calib import save_camera

    from .synth_samples import camera_from_meta

    meta_p = Path(photo).with_suffix(".json")
    try:
        cam = camera_from_meta(json.loads(meta_p.read_text()))
    except (OSError, ValueError, KeyError, TypeError):
        raise BenchError(f"{photo}: no --calib given and no dbh synth camera in {meta_p}") from None
    out = Path(folder) / "cam.yaml"
    save_camera(cam, out)
    return out


def run_bench(backend: Backend, photo: str, calib: str, *, pick_xy=None, repeat: int = 5, warmup: int = 1,
              timeout_s: float = 900.0) -> tuple[dict, float]:
    """Run the benchmark process; its record (see :func:`bench_child`) and the spawn time.

    Returns
    -------
    (dict, float)
        The child's record and ``time.time()`` just before the process was started (start-up is
        measured from it).

    Raises
    ------
    BenchError
        The process timed out, printed no record, or could not set up the measure function.
    """
    import subprocess
    import sys

    args = {"measure": backend.measure, "session": backend.session, "models_dir": backend.models_dir,
            "photo": str(photo), "calib": str(calib), "pick_xy": pick_xy, "repeat": repeat, "warmup": warmup}
    t_spawn = time.time()
    try:
        proc = subprocess.run([sys.executable, "-c", BENCH_CHILD_CODE, json.dumps(args)],
                              capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        raise BenchError(f"benchmark process did not finish in {timeout_s:.0f} s") from None
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith(BENCH_MARK)]
    if not lines:
        tail = " ".join(proc.stderr.strip().splitlines()[-1:]) or f"exit status {proc.returncode}"
        raise BenchError(f"benchmark process failed ({tail})")
    d = json.loads(lines[-1][len(BENCH_MARK):])
    if "error" in d:
        raise BenchError(d["error"])
    return d, t_spawn


BENCH_MARK = "MONODBH_BENCH "

#: Code run by ``python -c`` in the fresh benchmark process; ``t0`` is taken before any import.
BENCH_CHILD_CODE = ("import time; t0 = time.perf_counter(); w0 = time.time(); import sys; "
                    "from monodbh.toolkit.evaluation.speed_bench import bench_child; sys.exit(bench_child(t0, w0, sys.argv[1]))")


def _maxrss_mib() -> float:
    import resource
    import sys

    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / 2**20 if sys.platform == "darwin" else rss / 1024.0


def bench_child(t0: float, wall0: float, args_json: str) -> int:
    """Body of the benchmark process: time imports, session creation and repeated measures.

    Prints one line ``MONODBH_BENCH {json}`` on stdout with ``import_s``, ``session_s``,
    ``ready_wall`` (``time.time()`` when ready), ``rss_startup_mib``, ``runs`` (list of
    ``{"wall_ms", "timings_ms", "error"}``, warm-up runs first) and ``rss_peak_mib``. Returns the
    exit status (1 on a setup error, reported as ``{"error": ...}``).
    """
    import sys

    args = json.loads(args_json)

    def emit(d: dict) -> None:
        sys.stdout.write(BENCH_MARK + json.dumps(d, default=json_default) + "\n")
        sys.stdout.flush()

    try:
        backend = Backend(measure=args["measure"], session=args.get("session"),
                          models_dir=args.get("models_dir"))
        fn = backend.function()
        t_import = time.perf_counter()
        session = backend.new_session()
        t_session = time.perf_counter()
        ready_wall = time.time()
        rss_startup = _maxrss_mib()
        from monodbh.calib import load_camera

        camera = load_camera(args["calib"])
    except Exception as exc:
        emit({"error": str(exc) if isinstance(exc, MonodbhError)
              else f"internal error: {type(exc).__name__}: {one_line(exc)}"})
        return 1
    runs = []
    pick = tuple(args["pick_xy"]) if args.get("pick_xy") else None
    for _ in range(int(args.get("warmup", 1)) + int(args.get("repeat", 5))):
        t = time.perf_counter()
        res = run_job(Job(0, args["photo"], camera, pick_xy=pick), fn, session)
        runs.append({"wall_ms": (time.perf_counter() - t) * 1000.0, "timings_ms": res.timings_ms,
                     "error": res.error})
    emit({"import_s": t_import - t0, "session_s": t_session - t_import, "start_wall": wall0,
          "ready_wall": ready_wall, "rss_startup_mib": rss_startup, "runs": runs,
          "rss_peak_mib": _maxrss_mib()})
    return 0


def bench_report(d: dict, t_spawn: float, size: tuple[int, int], warmup: int) -> dict:
    """Numbers of ``dbh bench`` from the child's record ``d`` (see :func:`bench_child`)."""
    from .synth_eval import stage_stats

    runs = d["runs"][warmup:] or d["runs"]
    walls = [r["wall_ms"] for r in runs]
    stages = stage_stats([r["timings_ms"] for r in runs])
    mp = size[0] * size[1] / 1e6
    total_s = statistics.median(walls) / 1000.0
    startup_s = d["ready_wall"] - t_spawn
    peak = d["rss_peak_mib"]
    return {
        "photo_size": list(size), "megapixels": mp,
        "startup_s": startup_s, "interpreter_s": d["start_wall"] - t_spawn, "import_s": d["import_s"],
        "session_s": d["session_s"],
        "first_run_s": d["runs"][0]["wall_ms"] / 1000.0,
        "per_photo_s": total_s, "per_photo_min_s": min(walls) / 1000.0,
        "stages_ms": {k: v["median"] for k, v in stages.items()},
        "rss_startup_mib": d["rss_startup_mib"], "peak_mib": peak, "repeat": len(runs),
        "targets": BENCH_TARGETS,
        "pass": {"startup_s": startup_s <= BENCH_TARGETS["startup_s"],
                 "per_photo_s": total_s <= BENCH_TARGETS["per_photo_s"],
                 "peak_mib": peak <= BENCH_TARGETS["peak_mib"]},
    }


def print_bench(r: dict, console) -> None:
    """Print the table of ``dbh bench`` (``r`` from :func:`bench_report`)."""
    from rich.table import Table
    from rich.text import Text

    def ok(key):
        return Text("ok", style="green") if r["pass"][key] else Text("MISSED", style="bold red")

    t = Table(title=f"dbh bench ({r['photo_size'][0]}x{r['photo_size'][1]}, {r['megapixels']:.1f} MP, "
                    f"median of {r['repeat']})", show_header=True, header_style="bold")
    t.add_column("")
    t.add_column("value", justify="right")
    t.add_column("target", justify="right")
    t.add_column("")
    tg = r["targets"]
    t.add_row("start-up (new process -> ready)", f"{r['startup_s']:.2f} s", f"<= {tg['startup_s']:.1f} s",
              ok("startup_s"))
    t.add_row("  python start", f"{r['interpreter_s']:.2f} s", "", "")
    t.add_row("  imports", f"{r['import_s']:.2f} s", "", "")
    t.add_row("  session (models)", f"{r['session_s']:.2f} s", "", "")
    t.add_row("first measurement", f"{r['first_run_s']:.3f} s", "", "")
    for k, v in r["stages_ms"].items():
        if k != "total":
            # the segmenter and the depth network run on a thread beside the rope search: their
            # stages are the time waited for them
            name = f"{k} (wait; runs beside rope)" if k in ("segment", "depth") else k
            t.add_row(f"  stage {name}", f"{v:.1f} ms", "", "")
    t.add_row("per photo (wall, median)", f"{r['per_photo_s']:.3f} s", f"<= {tg['per_photo_s']:.1f} s",
              ok("per_photo_s"))
    t.add_row("  min", f"{r['per_photo_min_s']:.3f} s", "", "")
    if abs(r["megapixels"] - 12.0) > 1.0:
        # photos are measured at 1600 px (long side): the time does not scale with the pixels;
        # only decoding and the first resize grow with them (12 MP: +80-150 ms)
        t.add_row("  (the target is for a 12 MP photo: bench one)", "", "", "")
    t.add_row("memory after start-up", f"{r['rss_startup_mib']:.0f} MiB", "", "")
    t.add_row("peak memory (ru_maxrss)", f"{r['peak_mib']:.0f} MiB", f"<= {tg['peak_mib'] / 1024:.1f} GiB",
              ok("peak_mib"))
    console.print(t)
