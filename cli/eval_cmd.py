"""``dbh eval`` (accuracy on a ``dbh synth`` folder) and ``dbh bench`` (start-up, latency, memory).

The commands only; their logic is ``monodbh.toolkit.evaluation.synth_eval`` and
``monodbh.toolkit.evaluation.speed_bench``. Top-level imports stay light (typer only).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from .measure_cmd import fail, make_backend, measure_fn_option, parse_pick, session_factory_option

__all__ = ["evaluate", "bench"]


# -- dbh eval -----------------------------------------------------------------------------------
def evaluate(
    folder: Path = typer.Argument(..., help="Dataset folder written by dbh synth.", show_default=False),
    limit: Optional[int] = typer.Option(None, "--limit", "-n", min=1, help="Evaluate the first N samples.",
                                        show_default=False),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the report (metrics, per-stage "
                                            "times, per-sample rows) as JSON here.", show_default=False),
    gt_perception: bool = typer.Option(False, "--gt-perception", help="Measure from the ground-truth "
                                       "masks and depth instead of the networks (the single-view floor; "
                                       "needs no models)."),
    tap_base: bool = typer.Option(False, "--tap-base", help="Simulate a user who taps the stem base "
                                  "(dbh measure --base) in every photo where it is visible: the true "
                                  "base pixel plus Gaussian noise of --tap-noise-px."),
    tap_noise_px: float = typer.Option(3.0, "--tap-noise-px", min=0.0, help="1-sigma of the simulated "
                                       "tap, in pixels per axis (seeded per sample)."),
    tap_rope: bool = typer.Option(False, "--tap-rope", help="Simulate a user who taps the rope (dbh "
                                  "measure --pick) in every photo where it is visible: the middle of its "
                                  "visible pixels plus Gaussian noise of --tap-noise-px."),
    rope_known: bool = typer.Option(False, "--rope-known", help="Simulate a user who gives the rope's "
                                    "diameter (dbh measure --rope-mm): each sample's true rope diameter; rope-free "
                                    "samples get the median of the roped ones' (the marker the user carries)."),
    rope_mm: Optional[float] = typer.Option(None, "--rope-mm", min=1.0, max=100.0, help="Simulate a user "
                                            "whose marker width is set (dbh marker, or --rope-mm) for every "
                                            "photo, rope-free ones included: this width, mm.", show_default=False),
    workers: int = typer.Option(1, "--workers", "-j", min=1, help="Processes measuring in parallel."),
    out_dir: Optional[Path] = typer.Option(None, "--out-dir", help="Write overlays (and tree PLYs) here.",
                                           show_default=False),
    models_dir: Optional[Path] = typer.Option(None, "--models-dir", help="Folder of the ONNX models.",
                                              show_default=False),
    measure_fn: Optional[str] = measure_fn_option(),
    session_factory: Optional[str] = session_factory_option(),
    heldout: Optional[Path] = typer.Option(None, "--heldout", help="Also evaluate this folder (the same "
                                           "scenes in the held-out look: dbh synth --look heldout, same "
                                           "seed) and print both side by side; the JSON report gets it "
                                           "under \"heldout\".", show_default=False),
) -> None:
    """Measure every sample of a synthetic folder and compare with the roped tree's true DBH.

    Each sample is measured with a camera built from its K/dist. Prints DBH MAE, relative MAE,
    RMSE, bias, detection rate, sigma coverage, the correct-refusal rate on scenes without rope
    and the mean/median time per stage.
    """
    import sys

    from rich.console import Console

    from monodbh.toolkit.evaluation import synth_eval as se
    from monodbh.toolkit.outputs.atomic import atomic_write_text

    for f in (folder, heldout):
        if f is not None and not f.is_dir():
            raise fail(f"{f}: no such folder", 2)
    if rope_known and rope_mm is not None:
        raise typer.BadParameter("give --rope-known or --rope-mm, not both", param_hint="--rope-mm")
    opts = dict(limit=limit, gt_perception=gt_perception, tap_base=tap_base, tap_rope=tap_rope,
                tap_noise_px=tap_noise_px, rope_known=rope_known, rope_mm=rope_mm)
    backend = _eval_backend(measure_fn, session_factory, models_dir, gt_perception)
    err_console = Console(stderr=True)
    report, interrupted = _eval_folder(folder, backend, workers, out_dir, err_console, **opts)
    if heldout is not None and not interrupted:
        ho_out = None if out_dir is None else out_dir / "heldout"
        report["heldout"], interrupted = _eval_folder(heldout, backend, workers, ho_out, err_console, **opts)
        se.print_side_by_side({f"{folder.name} ({report['look']})": report["metrics"],
                               f"{heldout.name} ({report['heldout']['look']})": report["heldout"]["metrics"]},
                              Console())
    if json_out:
        atomic_write_text(json_out, json.dumps(report, indent=1, ensure_ascii=False) + "\n")
        err_console.print(f"report: {json_out}", highlight=False)
    if interrupted:
        err_console.print("interrupted", style="yellow")
        raise typer.Exit(130)
    sys.stdout.flush()


def _eval_folder(folder: Path, backend, workers: int, out_dir: Optional[Path], err_console, *,
                 limit: Optional[int], gt_perception: bool, tap_base: bool, tap_rope: bool,
                 tap_noise_px: float, rope_known: bool, rope_mm: Optional[float] = None) -> tuple[dict, bool]:
    """Measure one folder's samples and print its tables: ``(report, interrupted)``, the report as
    :func:`~monodbh.toolkit.evaluation.synth_eval.eval_report` writes it, plus the folder's ``look``."""
    from rich.console import Console

    from monodbh.calib import MonodbhError
    from monodbh.toolkit.evaluation import synth_eval as se
    from monodbh.toolkit.evaluation.synth_samples import list_synth_samples

    need_npz = gt_perception or tap_base or tap_rope
    idx = list_synth_samples(folder, need_npz=need_npz)
    if limit:
        idx = idx[:limit]
    if not idx:
        raise fail(f"{folder}: no samples (NNNNNN.jpg + .json{' + .npz' if need_npz else ''})")
    try:
        samples = se.read_eval_samples(folder, idx)
    except se.SampleRecordError as exc:
        raise fail(str(exc))
    jobs = se.eval_jobs(samples, tap_base=tap_base, tap_rope=tap_rope, tap_noise_px=tap_noise_px,
                        rope_known=rope_known, rope_mm=rope_mm, out_dir=out_dir)
    try:
        records, interrupted = _measure_all(jobs, samples, backend, workers, err_console)
    except MonodbhError as exc:
        raise fail(str(exc))
    if not records:
        raise fail(f"{folder}: interrupted before any sample was measured", 130)
    m = se.eval_metrics(records)
    stages = se.stage_stats([r["timings_ms"] for r in records])
    look = samples[0].meta.get("look", "default")
    console = Console()
    console.print(f"[bold]{folder}[/bold] ({look} look)", highlight=False)
    se.print_eval(m, stages, console)
    report = se.eval_report(folder, records, jobs, m, stages, gt_perception=gt_perception,
                            tap_base=tap_base, tap_rope=tap_rope, tap_noise_px=tap_noise_px,
                            rope_known=rope_known, interrupted=interrupted, rope_mm=rope_mm)
    report["look"] = look
    if interrupted:
        err_console.print(f"{folder}: interrupted after {len(records)} of {len(jobs)} samples", style="yellow")
    return report, interrupted


def _eval_backend(measure_fn: Optional[str], session_factory: Optional[str], models_dir: Optional[Path],
                  gt_perception: bool):
    """The backend of ``dbh eval``: with ``--gt-perception`` the ground-truth measure function,
    which needs no networks (no session unless one is asked for; a missing one is no error)."""
    import dataclasses

    if not gt_perception:
        return make_backend(measure_fn, session_factory, models_dir)
    from monodbh.toolkit.evaluation.ground_truth import GT_MEASURE

    backend = make_backend(measure_fn, session_factory, models_dir, default_fn=GT_MEASURE)
    if measure_fn is None and session_factory is None:
        backend = dataclasses.replace(backend, session=None)
    return dataclasses.replace(backend, session_optional=True)


def _measure_all(jobs, samples, backend, workers: int, err_console) -> tuple[list[dict], bool]:
    """Measure the jobs with a progress bar; the report rows so far and whether Ctrl-C stopped it."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from monodbh.toolkit.batch import iter_results
    from monodbh.toolkit.evaluation.synth_eval import eval_record

    records: list[dict] = []
    try:
        with Progress(TextColumn("[progress.description]{task.description}"), BarColumn(),
                      MofNCompleteColumn(), TimeRemainingColumn(), console=err_console,
                      transient=True) as prog:
            task = prog.add_task("evaluating", total=len(jobs))
            for res, s in zip(iter_results(jobs, backend, workers=workers), samples):
                records.append(eval_record(s, res.to_json_dict()))
                prog.advance(task)
    except KeyboardInterrupt:
        return records, True
    return records, False


# -- dbh bench ----------------------------------------------------------------------------------
def bench(
    photo: str = typer.Argument(..., help="Photo to measure repeatedly (a 12 MP phone photo for the "
                                "acceptance check).", show_default=False),
    calib: Optional[Path] = typer.Option(None, "--calib", "-c", help="Camera file (default: the camera "
                                         "of a `dbh synth` photo, from its .json beside it).",
                                         show_default=False),
    repeat: int = typer.Option(5, "--repeat", "-r", min=1, help="Timed measurements (after warm-up)."),
    warmup: int = typer.Option(1, "--warmup", min=0, help="Untimed measurements first."),
    pick: Optional[str] = typer.Option(None, "--pick", metavar="X,Y", help="Pixel on the roped tree.",
                                       show_default=False),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the numbers as JSON here.",
                                            show_default=False),
    check: bool = typer.Option(False, "--check", help="Exit 1 when a target is missed."),
    timeout: float = typer.Option(900.0, "--timeout", min=1.0, help="Seconds before the benchmark "
                                  "process is stopped."),
    models_dir: Optional[Path] = typer.Option(None, "--models-dir", help="Folder of the ONNX models.",
                                              show_default=False),
    measure_fn: Optional[str] = measure_fn_option(hidden=False),
    session_factory: Optional[str] = session_factory_option(hidden=False),
) -> None:
    """Benchmark a measure function in a fresh process: start-up, per-stage latency, memory.

    Start-up = Python start + imports + session creation, measured in a new process; latency
    = median over --repeat measurements after --warmup; peak memory = ru_maxrss of that
    process. Targets: <= 1.0 s per 12 MP photo after start-up, start-up <= 2 s, peak <= 1.5 GiB.
    """
    from rich.console import Console

    from monodbh.calib import MonodbhError, read_image_size
    from monodbh.toolkit.evaluation.speed_bench import bench_report, print_bench, run_bench, synth_camera_file
    from monodbh.toolkit.outputs.atomic import atomic_write_text

    pick_xy = parse_pick(pick)
    if not Path(photo).is_file():
        raise fail(f"{photo}: no such file")
    try:
        if calib is None:
            # a `dbh synth` photo: its camera is in the sample's .json (a temporary cam.yaml from it)
            import atexit
            import shutil
            import tempfile

            tmp = tempfile.mkdtemp(prefix="monodbh_bench_")
            atexit.register(shutil.rmtree, tmp, True)
            calib = synth_camera_file(photo, tmp)
        if not calib.is_file():
            raise fail(f"{calib}: no such file")
        w, h = read_image_size(photo)
        backend = make_backend(measure_fn, session_factory, models_dir)
        err_console = Console(stderr=True)
        with err_console.status(f"benchmarking {backend.measure} ({warmup} + {repeat} runs)"):
            d, t_spawn = run_bench(backend, str(photo), str(calib), pick_xy=pick_xy, repeat=repeat,
                                   warmup=warmup, timeout_s=timeout)
    except MonodbhError as exc:
        raise fail(str(exc))
    report = bench_report(d, t_spawn, (w, h), warmup)
    print_bench(report, Console())
    for e in {r["error"] for r in d["runs"] if r["error"]}:
        err_console.print(f"warning: the measurement failed: {e}", style="yellow", highlight=False)
    if json_out:
        atomic_write_text(json_out, json.dumps({**report, "measure": backend.measure, "photo": str(photo),
                                                "runs": d["runs"]}, indent=1) + "\n")
    if check and not all(report["pass"].values()):
        raise typer.Exit(1)
