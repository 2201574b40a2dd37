"""Logic of ``dbh export RUN_DIR [--ship]`` (the typer command only calls :func:`export_run`).

Writes ``RUN_DIR/export/{kind}_fp32.onnx``, ``{kind}_int8.onnx`` (only when an int8 recipe
passes the accuracy gate) and ``report.json``; with ``ship=True`` copies the int8 model to
``models/{kind}_int8.onnx`` and updates ``models/manifest.json`` (schema in :func:`manifest_entry`).
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import hashlib
import json
import os
import shutil
from pathlib import Path
from typing import Any, Sequence

from monodbh.models.export.onnx_io import export_onnx, make_session, run_session
from monodbh.models.export.quantize import DEFAULT_RECIPES, QuantRecipe, search_int8
from monodbh.models.modeling.registry import ModelSpec
from monodbh.models.runtime.common import MonodbhError, load_manifest

__all__ = ["export_run", "ship_model", "manifest_entry", "sha256_file", "shipped_spec", "MODELS_DIR",
           "MANIFEST_NAME"]

#: Folder of the shipped models (the ``monodbh.models`` package folder).
MODELS_DIR = Path(__file__).resolve().parents[1]
MANIFEST_NAME = "manifest.json"


def _error(msg: str) -> Exception:
    from monodbh.calib.errors import MonodbhError

    return MonodbhError(msg)


def sha256_file(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _source_or_none(cfg: dict[str, Any] | None):
    """Rebuild a data source from config.json (None if absent or not rebuildable)."""
    from monodbh.models.training.common import source_from_config

    if not cfg:
        return None
    try:
        return source_from_config(cfg)
    except Exception:  # noqa: BLE001 - the kind's hook falls back to its default data
        return None


def shipped_spec(spec: ModelSpec, shipped_path: Path) -> ModelSpec:
    """The shipped file's own spec (its manifest entry: input size, kind-specific constants such
    as the tree network's ``thickness``), so that it is scored by its own conventions on the same
    data; ``spec`` when the manifest has no usable entry."""
    try:
        entry = load_manifest(shipped_path.parent / "manifest.json")["models"][spec.kind]
        old = ModelSpec.from_dict(entry["spec"])
    except (OSError, KeyError, ValueError, TypeError, MonodbhError):
        return spec
    if spec.kind == "tree" and "thickness" not in old.extra:
        old = dataclasses.replace(old, extra={**old.extra, "thickness": "z"})   # runs that measured the thickness in z
    return old


def manifest_entry(spec: ModelSpec, file_name: str, sha256: str, report: dict[str, Any]) -> dict[str, Any]:
    """One ``models/manifest.json`` entry (``manifest["models"][kind]``).

    Keys: ``file``, ``sha256``, ``precision``, ``quant_recipe``, ``inputs``/``outputs``
    (name, shape, dtype), ``preprocess`` (normalisation), ``classes``, ``extra`` (e.g. depth
    mapping), ``metric``, ``spec`` (the full :meth:`ModelSpec.to_dict`), ``training``
    (seed, steps, size, run), ``validation`` (``fp32``/``int8`` metric dicts), ``latency_ms``
    (``fp32``/``int8`` medians, ``threads``), ``exported_at``.
    """
    d = spec.to_dict()
    return {
        "file": file_name, "sha256": sha256, "precision": "int8",
        "quant_recipe": report.get("int8", {}).get("recipe"),
        "inputs": [{k: t[k] for k in ("name", "shape", "dtype")} for t in d["inputs"]],
        "outputs": [{k: t[k] for k in ("name", "shape", "dtype")} for t in d["outputs"]],
        "preprocess": d["preprocess"], "classes": d["classes"], "extra": d["extra"],
        "metric": {"name": spec.metric, "higher_is_better": spec.higher_is_better},
        "spec": d,
        "training": report.get("training", {}),
        "validation": {"fp32": report.get("fp32", {}).get("metrics", {}),
                       "int8": report.get("int8", {}).get("metrics", {})},
        "latency_ms": {"fp32": report.get("fp32", {}).get("latency_ms"),
                       "int8": report.get("int8", {}).get("latency_ms"),
                       "threads": report.get("threads", 2)},
        "exported_at": report.get("exported_at"),
    }


def ship_model(kind: str, int8_path: str | os.PathLike, spec: ModelSpec, report: dict[str, Any],
               models_dir: str | os.PathLike | None = None) -> dict[str, Any]:
    """Copy ``int8_path`` to ``models_dir/{kind}_int8.onnx`` and update the manifest atomically."""
    from monodbh.models.training.common import atomic_write_text

    models_dir = Path(models_dir) if models_dir is not None else MODELS_DIR
    models_dir.mkdir(parents=True, exist_ok=True)
    name = f"{kind}_int8.onnx"
    tmp = models_dir / (name + ".tmp")
    shutil.copyfile(int8_path, tmp)
    os.replace(tmp, models_dir / name)
    man_path = models_dir / MANIFEST_NAME
    manifest = load_manifest(man_path)     # (a manifest of the networks' old kinds: under today's)
    manifest.setdefault("format", 1)
    manifest.setdefault("models", {})
    entry = manifest_entry(spec, name, sha256_file(models_dir / name), report)
    manifest["models"][kind] = entry
    atomic_write_text(man_path, json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    return entry


def export_run(run_dir: str | os.PathLike, ship: bool = False, n_calib: int = 32,
               tolerance: float = 0.03, *, n_eval: int | None = None,
               recipes: Sequence[QuantRecipe] | None = None, n_runs: int = 20,
               threads: int = 2, models_dir: str | os.PathLike | None = None,
               data: Any = None, val_data: Any = None, max_rel_l2: float | None = None,
               verbose: bool = True, force: bool = False) -> dict[str, Any]:
    """Export a training run: fp32 ONNX (checked against torch), int8 search, report, ship.

    Parameters
    ----------
    run_dir : path
        Training run folder (config.json + checkpoint.pt, see ``training.common``).
    ship : bool
        Copy the int8 model into the package's ``models/`` and update ``manifest.json``.
        Raises the user error ``MonodbhError`` when no int8 recipe passed the accuracy gate.
    n_calib : int
        Calibration samples (from the run's training data, via the kind's calibration hook).
    tolerance : float
        Largest accepted relative loss of the task metric (``spec.metric``) int8 vs fp32.
    n_eval : int, optional
        Evaluation samples for metric/rel-L2/latency (run's validation data); default ``n_calib``.
    recipes : list of QuantRecipe, optional
        Default :data:`~monodbh.models.export.quantize.DEFAULT_RECIPES`.
    models_dir : path, optional
        Ship destination (default: the installed ``monodbh/models`` folder).
    force : bool
        Ship even when the model shipped now scores better on the same evaluation data
        (``report["previous"]``).
    max_rel_l2 : float, optional
        Also require the int8 outputs' relative L2 error to stay below this (always applied,
        at 0.05, when the fp32 task metric is ~0, i.e. an untrained model).
    data, val_data : optional
        Override the calibration / evaluation data (anything ``training.common.make_source``
        accepts); default: rebuilt from the run's config.json, else the kind's default.

    Returns
    -------
    dict
        The report (also written to ``RUN_DIR/export/report.json``): kind, size, training,
        fp32 {path, check, metrics, latency_ms}, int8 {path, recipe, metrics, latency_ms, drop}
        or ``None``, quantization {rows, table, errors}, shipped entry or ``None``.
    """
    from monodbh.models.training.common import (RunDir, atomic_write_text, calibration_inputs,
                                                evaluate_kind, load_run_model)

    run = RunDir(run_dir)
    if not run.config_path.exists() or not run.checkpoint_path.exists():
        raise _error(f"{run.path}: not a finished training run (config.json/checkpoint.pt missing)")
    model, config, ckpt = load_run_model(run.path)
    spec: ModelSpec = model.spec
    kind = spec.kind
    if kind == "tree" and "thickness" in spec.extra:
        # how the run's targets measured the thickness (older runs: in z)
        spec = dataclasses.replace(spec, extra={**spec.extra,
                                                "thickness": config.get("train", {}).get("thickness", "z")})
    seed = int(config.get("seed", 0))
    out = run.export_dir
    out.mkdir(parents=True, exist_ok=True)
    fp32_path = out / f"{kind}_fp32.onnx"
    int8_path = out / f"{kind}_int8.onnx"

    check = export_onnx(model, spec, fp32_path, check=True)
    from monodbh.models.training.common import make_source

    train_src = make_source(data) if data is not None else _source_or_none(config.get("data"))
    val_src = (make_source(val_data) if val_data is not None
               else _source_or_none(config.get("val_data")))
    calib = calibration_inputs(kind, n_calib, seed + 101, spec, train_src)
    n_eval = n_eval or n_calib
    eval_feeds = calibration_inputs(kind, n_eval, seed + 202, spec, val_src)

    def metric_fn(predict, spec_=spec):
        return evaluate_kind(kind, predict, n_eval, seed + 303, spec_, val_src)

    res = search_int8(fp32_path, int8_path, calib, eval_feeds, spec, metric_fn=metric_fn,
                      recipes=recipes or DEFAULT_RECIPES, tolerance=tolerance,
                      max_rel_l2=max_rel_l2, n_runs=n_runs,
                      threads=threads, verbose=verbose)
    rows = {r["model"]: r for r in res["rows"]}
    fp32_row = rows.get("fp32")
    if fp32_row is None:  # every recipe failed before measuring: measure fp32 alone
        sess = make_session(fp32_path, threads=threads)
        fp32_row = {"metrics": metric_fn(lambda f: run_session(sess, f)), "latency_ms": None}
    report: dict[str, Any] = {
        "kind": kind, "size": spec.size,
        "exported_at": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "threads": threads, "tolerance": tolerance,
        "training": {"seed": seed, "steps": int(ckpt.get("step", config.get("steps", 0))),
                     "size": spec.size, "run": str(run.path.resolve()),
                     "init_weights": config.get("init_weights"),
                     "total_steps": int(ckpt.get("step", config.get("steps", 0)))
                     + int((config.get("init_weights") or {}).get("from_step") or 0),
                     "data": config.get("data"), "val_data": config.get("val_data"),
                     **({"augment": config["aug"]} if config.get("aug") else {}),
                     **({"blend": config["blend"]} if config.get("blend") else {})},
        "fp32": {"path": str(fp32_path), "check": check, "metrics": fp32_row.get("metrics", {}),
                 "latency_ms": fp32_row.get("latency_ms"),
                 "size_mb": fp32_path.stat().st_size / 2**20},
        "int8": None,
        "quantization": {"rows": res["rows"], "table": res["table"], "errors": res["errors"],
                         "chosen": res["chosen"], "recipe": res["recipe"]},
        "shipped": None,
    }
    if res["chosen"]:
        r = rows[res["chosen"]]
        report["int8"] = {"path": str(int8_path), "recipe": res["chosen"],
                          "metrics": r.get("metrics", {}), "latency_ms": r["latency_ms"],
                          "drop": r["drop"], "rel_l2": r["rel_l2"], "size_mb": r["size_mb"]}
    # the model shipped now, scored on the same evaluation data: a new model replaces it only
    # when it is at least as good on the task metric (unless force)
    shipped_path = (Path(models_dir) if models_dir is not None else MODELS_DIR) / f"{kind}_int8.onnx"
    report["previous"] = None
    if shipped_path.exists():
        try:
            prev_sess = make_session(shipped_path, threads=threads)
            prev = metric_fn(lambda f, _s=prev_sess: run_session(_s, f), shipped_spec(spec, shipped_path))
            report["previous"] = {"path": str(shipped_path), "sha256": sha256_file(shipped_path),
                                  "metrics": prev}
        except Exception as e:  # noqa: BLE001 - another architecture/spec: nothing to compare
            report["previous"] = {"path": str(shipped_path), "error": f"{type(e).__name__}: {e}"}
    if verbose and report["previous"] and "metrics" in report["previous"] and report["int8"]:
        pm, nm = report["previous"]["metrics"], report["int8"]["metrics"]
        keys = [k for k in nm if k in pm and isinstance(nm[k], (int, float))]
        print(f"{'metric':<16}{'shipped int8':>14}{'new int8':>12}")
        for k in keys:
            print(f"{k:<16}{pm[k]:>14.4f}{nm[k]:>12.4f}")
    if ship:
        prev_m = ((report.get("previous") or {}).get("metrics") or {}).get(spec.metric)
        new_m = (report["int8"] or {}).get("metrics", {}).get(spec.metric)
        if (not force and prev_m is not None and new_m is not None
                and (new_m < prev_m if spec.higher_is_better else new_m > prev_m)):
            atomic_write_text(out / "report.json", json.dumps(report, indent=2, default=str) + "\n")
            raise _error(f"{run.path}: the new int8 model scores {spec.metric} {new_m:.4f}, the shipped "
                         f"one {prev_m:.4f} on the same data; nothing shipped (--force to ship anyway)")
        if report["int8"] is None:
            atomic_write_text(out / "report.json", json.dumps(report, indent=2, default=str) + "\n")
            raise _error(f"{run.path}: no int8 model within {tolerance:.1%} of fp32 on "
                         f"{spec.metric}; nothing shipped (see {out / 'report.json'})")
        report["shipped"] = ship_model(kind, int8_path, spec, report, models_dir)
    atomic_write_text(out / "report.json", json.dumps(report, indent=2, default=str) + "\n")
    return report
