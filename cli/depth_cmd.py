"""``dbh depth`` (metric depth maps of photos) and ``dbh eval-depth`` (scores on a synth folder)."""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer


def depth(
    photos: List[Path] = typer.Argument(..., help="Photos."),
    calib: Path = typer.Option(..., "--calib", "-c", help="cam.yaml"),
    out_dir: Path = typer.Option(..., "--out-dir", "-o", help="Writes <photo stem>_depth.npy (float32 metres)."),
    models_dir: Optional[Path] = typer.Option(None, "--models-dir", hidden=True),
) -> None:
    """Metric z-depth (metres, float32) at each photo's resolution from the depth network.

    Exit status: 0 when every photo was done, 1 when some failed (each reported on one line, the
    others still written), 2 on usage errors (an output that would overwrite an input).
    """
    import numpy as np

    from monodbh.calib.errors import MonodbhError
    from monodbh.toolkit.batch import error_result
    from monodbh.toolkit.evaluation.depth_eval import depth_file, photo_depth, write_depth
    from monodbh.toolkit.outputs.paths import ensure_folder, printable
    from monodbh.toolkit.pipeline import Session

    from .measure_cmd import check_outputs, fail, load_calib

    cam = load_calib(calib)
    check_outputs([*photos, calib], out_dir=out_dir, planned=[depth_file(out_dir, str(p)) for p in photos])
    try:
        ensure_folder(out_dir, "--out-dir")
        sess = Session(models_dir)
    except MonodbhError as e:
        raise fail(str(e))
    failed = 0
    for p in photos:
        try:
            d, tm = photo_depth(str(p), cam, sess)
            out = write_depth(out_dir, str(p), d)
            typer.echo(printable(f"{p}: {out} ({d.shape[1]}x{d.shape[0]}, median {float(np.median(d)):.2f} m, "
                                 f"{sum(tm.values()):.0f} ms)"), err=True)
        except MonodbhError as e:
            failed += 1
            fail(str(e) if str(e).startswith(str(p)) else f"{p}: {e}")
        except Exception as e:  # noqa: BLE001 - reported, and the next photo goes on
            failed += 1
            fail(error_result(str(p), e).error)
    raise typer.Exit(1 if failed else 0)


def eval_depth(
    folder: Path = typer.Argument(..., exists=True, file_okay=False, help="A dbh synth folder."),
    limit: Optional[int] = typer.Option(None, "--limit", "-n"),
    max_depth_m: float = typer.Option(80.0, "--max-depth-m", min=0.1, help="Score the pixels whose true "
                                      "depth is at most this (metres)."),
    heldout: Optional[Path] = typer.Option(None, "--heldout", exists=True, file_okay=False,
                                           help="Also score this folder (the same scenes in the held-out "
                                           "look, dbh synth --look heldout) and print it beside."),
    models_dir: Optional[Path] = typer.Option(None, "--models-dir", hidden=True),
) -> None:
    """Score the depth network on a dbh synth folder: AbsRel, SqRel, RMSE, RMSE-log, log10,
    delta < 1.25^k, in metric depth and median-scaled."""
    import numpy as np
    from rich.console import Console

    from monodbh.toolkit.evaluation.depth_eval import evaluate_depth, print_depth_scores
    from monodbh.toolkit.pipeline import Session
    sess = Session(models_dir)
    console = Console()
    for f in [folder] + ([heldout] if heldout is not None else []):
        ms, times = evaluate_depth(f, sess, limit, max_depth_m=max_depth_m)
        if not times:
            typer.echo(f"error: {f}: no samples", err=True)
            raise typer.Exit(1)
        print_depth_scores(ms, f"depth network on {f} ({len(ms)} photos, pixels within {max_depth_m:g} m)", console)
        typer.echo(f"{f}: depth network median latency {np.median(times):.0f} ms", err=True)
