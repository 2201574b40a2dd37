"""``dbh train`` and ``dbh export`` (training-only; need the ``train`` extra)."""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

#: the networks ``dbh train`` trains, by kind (the manifest's, the registry's and the file's name)
KINDS = ("segmenter", "depth", "tree", "stem_base", "stem_edge", "rope_verifier", "rope_finder")


def train(
    kind: str = typer.Argument(..., help="segmenter | depth | tree | stem_base (the stem-base finder) | stem_edge (the stem-edge finder) | rope_verifier (the rope-band verifier) | rope_finder (the mask-free rope finder)"),
    out: Path = typer.Option(..., "--out", "-o", help="Run folder (config.json, checkpoint.pt, log.jsonl)."),
    steps: int = typer.Option(20000, "--steps", min=1, help="Total optimiser steps."),
    resume: bool = typer.Option(False, "--resume", help="Continue from OUT/checkpoint.pt."),
    data: Optional[List[Path]] = typer.Option(None, "--data", help="dbh synth folder(s) (rope_verifier: .npz banks of `python -m monodbh.toolkit.evaluation.fit_rope_stem --bank`; rope_finder: of `python -m monodbh.models.training.rope_finder_bank`); default: render on the fly."),
    val: Optional[List[Path]] = typer.Option(None, "--val", help="Validation folder(s) (seeds never used in training)."),
    stop_at: Optional[int] = typer.Option(None, "--stop-at", help="Stop (checkpointed) after this many steps."),
    size: str = typer.Option("base", "--size", help="Model size: base | tiny | wide (depth/tree: the wider first-run configs) | base384 (segmenter), effl0 (segmenter, stem_base; needs the pretrained extra)."),
    batch_size: Optional[int] = typer.Option(None, "--batch-size"),
    crop: Optional[int] = typer.Option(None, "--crop", help="rope_finder: training window side in pixels (even; "
                                       "default 128, at most the bank's 192-pixel tiles)."),
    threads: Optional[int] = typer.Option(None, "--threads", help="CPU threads (default: all cores)."),
    init: Optional[Path] = typer.Option(None, "--init", exists=True, dir_okay=False,
                                        help="Warm start (new runs) from a shipped model, e.g. models/depth_int8.onnx, "
                                             "or a `dbh train-pack` weights file."),
    augment: Optional[str] = typer.Option(None, "--augment", help="Segmenter augmentation preset: default | "
                                          "strong (wider colour jitter)."),
    lr: Optional[float] = typer.Option(None, "--lr",
                                       help="Peak learning rate (depth and tree: the generator's); default: "
                                            "the kind's own."),
) -> None:
    """Train one of the networks on synthetic scenes (CPU, or CUDA when present)."""
    if kind not in KINDS:
        raise typer.BadParameter(f"kind must be one of {', '.join(KINDS)}, got {kind!r}")
    opts = {"size": size}
    if augment is not None:
        from monodbh.models.training.common import AUGMENT_PRESETS
        if kind != "segmenter":
            raise typer.BadParameter("only the segmenter takes an augmentation preset", param_hint="--augment")
        if augment not in AUGMENT_PRESETS:
            raise typer.BadParameter(f"expected one of {', '.join(AUGMENT_PRESETS)}, got {augment!r}",
                                     param_hint="--augment")
        opts["aug"] = AUGMENT_PRESETS[augment]
    if init is not None:
        opts["init_weights"] = str(init)
    if batch_size:
        opts["batch_size"] = batch_size
    if crop is not None:
        if kind != "rope_finder":
            raise typer.BadParameter("only the rope finder (rope_finder) takes a window size", param_hint="--crop")
        opts["crop"] = crop
    if threads:
        opts["threads"] = threads
    if lr is not None:
        if not lr > 0:
            raise typer.BadParameter(f"must be positive, got {lr}", param_hint="--lr")
        opts["lr_g" if kind in ("depth", "tree") else "lr"] = lr
    d = [str(p) for p in data] if data else None
    v = [str(p) for p in val] if val else None
    if kind == "segmenter":
        from monodbh.models.training.segmenter import train_segmenter
        res = train_segmenter(out, steps, data=d or "gen", resume=resume, val_data=v, stop_at=stop_at, **opts)
    elif kind == "depth":
        from monodbh.models.training.depth import train_depth
        res = train_depth(str(out), steps, data=d, resume=resume, val_data=v, stop_at=stop_at, **opts)
    elif kind == "stem_base":
        from monodbh.models.training.stem_base import train_stem_base
        res = train_stem_base(str(out), steps, data=d, resume=resume, val_data=v, stop_at=stop_at, **opts)
    elif kind == "stem_edge":
        from monodbh.models.training.stem_edge import train_stem_edge
        res = train_stem_edge(str(out), steps, data=d, resume=resume, val_data=v, stop_at=stop_at, **opts)
    elif kind == "rope_verifier":
        from monodbh.models.training.rope_verifier import train_rope_verifier
        res = train_rope_verifier(str(out), steps, data=d, resume=resume, val_data=v, stop_at=stop_at, **opts)
    elif kind == "rope_finder":
        from monodbh.models.training.rope_finder import train_rope_finder
        res = train_rope_finder(str(out), steps, data=d, resume=resume, val_data=v, stop_at=stop_at, **opts)
    else:
        from monodbh.models.training.tree import train_tree
        res = train_tree(str(out), steps, data=d, resume=resume, val_data=v, stop_at=stop_at, **opts)
    typer.echo(f"{kind}: stopped at step {res.get('step')}; validation {res.get('val')}", err=True)


def export(
    run_dir: Path = typer.Argument(..., exists=True, file_okay=False, help="Training run folder."),
    ship: bool = typer.Option(False, "--ship", help="Copy the int8 model into models/ and update the manifest."),
    n_calib: int = typer.Option(32, "--n-calib", help="Calibration samples for int8."),
    tolerance: float = typer.Option(0.03, "--tolerance", help="Max relative loss of the task metric for int8."),
    val: Optional[List[Path]] = typer.Option(None, "--val", help="Evaluation folder(s)."),
    n_eval: Optional[int] = typer.Option(None, "--n-eval", min=1, help="Evaluation samples (default: --n-calib)."),
    force: bool = typer.Option(False, "--force", help="Ship even if the shipped model scores better on the same data."),
    recipe: Optional[List[str]] = typer.Option(
        None, "--recipe", help="Only these int8 recipes (repeatable; names as in the export table). "
                               "One recipe makes the export reproducible: with several the fastest passing one "
                               "is kept, which depends on the measured latency."),
) -> None:
    """Export a run to ONNX fp32 and int8 (onnxruntime.quantization), print fp32-vs-int8 tables."""
    from monodbh.models.export.cli_impl import export_run
    from monodbh.models.export.quantize import recipes_by_name
    try:
        recipes = recipes_by_name(recipe) if recipe else None
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint="--recipe")
    export_run(run_dir, ship=ship, n_calib=n_calib, tolerance=tolerance, n_eval=n_eval,
               val_data=[str(p) for p in val] if val else None, force=force, recipes=recipes)


def train_pack(
    run_dir: Path = typer.Argument(..., exists=True, file_okay=False, help="Training run folder."),
    out: Path = typer.Option(..., "--out", "-o", help="Weights file to write (float16, weights only)."),
) -> None:
    """Pack a run's weights (float16, no optimiser) into one small file to commit and warm-start from."""
    from monodbh.models.training.common import pack_weights
    info = pack_weights(run_dir, out)
    typer.echo(f"{out}: {info['kind']}/{info['size']} step {info['step']}, {info['bytes'] / 1e6:.1f} MB", err=True)


def train_blend(
    run_dir: Path = typer.Argument(..., exists=True, file_okay=False, help="A finished warm-started run (--init)."),
    out: Path = typer.Option(..., "--out", "-o", help="New run folder to write (for dbh export)."),
    alpha: float = typer.Option(..., "--alpha", min=0.0, max=1.0,
                                help="The fine-tuned weights' share (1: the run as trained, 0: where it started)."),
    start: Optional[Path] = typer.Option(None, "--start", exists=True, dir_okay=False,
                                         help="The starting weights' ONNX file (default: the run's --init file)."),
) -> None:
    """Blend a fine-tuned run's weights with those it started from (WiSE-FT) into a new run folder."""
    from monodbh.models.training.blend import blend_run
    try:
        info = blend_run(run_dir, out, alpha, start=start)
    except (ValueError, FileExistsError, FileNotFoundError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1)
    typer.echo(f"{out}: alpha {info['alpha']} of {run_dir}, start {info['start']} ({info['start_sha256'][:12]})", err=True)
