"""int8 quantisation (onnxruntime.quantization) with an accuracy gate, and fp32-vs-int8 benchmark.

Recipes (:class:`QuantRecipe`) are tried by :func:`search_int8`; each candidate is measured
against the fp32 model in the same process (task metric from the kind, relative L2 of every
output, median latency with 2 intra-op threads, runs interleaved so background load hits all
models alike). A candidate losing more than ``tolerance`` (relative, default 3 %) on the task
metric is rejected; the fastest passing candidate is kept. If none passes, no int8 file is
written.
"""
from __future__ import annotations

import dataclasses
import os
import re
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import onnx

from monodbh.models.export.onnx_io import embed_spec, make_session, run_session
from monodbh.models.modeling.registry import ModelSpec

__all__ = ["QuantRecipe", "DEFAULT_RECIPES", "recipes_by_name", "FLOAT_OP_TYPES", "quantize_int8",
           "benchmark", "format_table", "search_int8", "metric_drop", "TABLE_COLUMNS", "preprocess_model"]

#: Op types kept in float by default (numerically sensitive, little speed gain).
FLOAT_OP_TYPES: tuple[str, ...] = ("LayerNormalization", "Softmax", "Gelu", "Erf", "Sigmoid",
                                   "ReduceMean", "Pow", "Sqrt", "Div", "Exp", "Where")


@dataclass(frozen=True)
class QuantRecipe:
    """One quantisation configuration.

    Parameters
    ----------
    name : str
        Label in tables/reports.
    mode : {"static", "dynamic", "static+dynamic"}
        ``static``: QDQ with calibration; ``dynamic``: weights int8, activations quantised at run
        time (MatMul/Gemm via ``quantize_dynamic``); ``static+dynamic``: static QDQ on
        ``op_types`` then dynamic on ``dynamic_op_types`` of the remaining float nodes.
    activation_type, weight_type : {"int8", "uint8"}
        S8S8 = ("int8", "int8"), U8S8 = ("uint8", "int8").
    per_channel, reduce_range : bool
    op_types : tuple of str or None
        Op types to quantise (``None``: all that onnxruntime supports).
    exclude_op_types : tuple of str
        Op types whose nodes are kept float.
    exclude_name_patterns : tuple of str
        Regular expressions (``re.search``) on node names kept float (e.g. ``"attn"``).
    calibrate_method : {"minmax", "percentile", "entropy"}
    dynamic_op_types : tuple of str
        For the dynamic stage.
    extra_options : dict
        Passed to onnxruntime (e.g. ``{"ActivationSymmetric": True}``).
    """

    name: str
    mode: str = "static"
    activation_type: str = "int8"
    weight_type: str = "int8"
    per_channel: bool = True
    reduce_range: bool = False
    op_types: tuple[str, ...] | None = None
    exclude_op_types: tuple[str, ...] = FLOAT_OP_TYPES
    exclude_name_patterns: tuple[str, ...] = ()
    calibrate_method: str = "minmax"
    dynamic_op_types: tuple[str, ...] = ("MatMul", "Gemm")
    extra_options: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


#: Searched in order: most aggressive (fastest) first, most conservative last.
DEFAULT_RECIPES: tuple[QuantRecipe, ...] = (
    # U8S8 with 7-bit weights: x86 CPUs without VNNI run U8S8 with VPMADDUBSW, which can
    # saturate with full-range weights (onnxruntime quantisation docs); the export machine may
    # have VNNI and would not see it, so the U8S8 recipes are always reduce_range.
    QuantRecipe("u8s8_qdq_all", activation_type="uint8", reduce_range=True),
    QuantRecipe("u8s8_qdq_conv_gemm", activation_type="uint8", reduce_range=True,
                op_types=("Conv", "Gemm", "MatMul"), exclude_name_patterns=("attn",)),
    QuantRecipe("u8s8_qdq_conv", activation_type="uint8", reduce_range=True, op_types=("Conv",)),
    QuantRecipe("s8s8_qdq_all"),
    QuantRecipe("s8s8_qdq_conv_percentile", op_types=("Conv",), calibrate_method="percentile",
                extra_options={"CalibPercentile": 99.99}),
    QuantRecipe("s8s8_conv+dynamic_matmul", mode="static+dynamic", op_types=("Conv",)),
    QuantRecipe("dynamic_matmul", mode="dynamic"),
)


def recipes_by_name(names: Sequence[str]) -> tuple[QuantRecipe, ...]:
    """The :data:`DEFAULT_RECIPES` named in ``names``, in the order given.

    Raises ``ValueError`` naming the unknown ones and the known names.

    Examples
    --------
    >>> [r.name for r in recipes_by_name(["u8s8_qdq_conv_gemm"])]
    ['u8s8_qdq_conv_gemm']
    """
    known = {r.name: r for r in DEFAULT_RECIPES}
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ValueError(f"unknown int8 recipe(s) {', '.join(unknown)}; known: {', '.join(known)}")
    return tuple(known[n] for n in dict.fromkeys(names))


TABLE_COLUMNS: tuple[str, ...] = ("model", "recipe", "size_mb", "latency_ms", "latency_p90_ms",
                                  "speedup", "rel_l2", "metric", "drop", "pass")


def _qtype(name: str):
    from onnxruntime.quantization import QuantType

    return {"int8": QuantType.QInt8, "uint8": QuantType.QUInt8}[name]


def _calib_method(name: str):
    from onnxruntime.quantization import CalibrationMethod

    return {"minmax": CalibrationMethod.MinMax, "percentile": CalibrationMethod.Percentile,
            "entropy": CalibrationMethod.Entropy}[name]


def preprocess_model(fp32_path: str | os.PathLike, out_path: str | os.PathLike) -> Path:
    """``quant_pre_process`` (shape inference + graph optimisation); falls back gracefully."""
    from onnxruntime.quantization.shape_inference import quant_pre_process

    out_path = Path(out_path)
    for kwargs in ({}, {"skip_symbolic_shape": True}, {"skip_optimization": True,
                                                       "skip_symbolic_shape": True}):
        try:
            quant_pre_process(str(fp32_path), str(out_path), **kwargs)
            return out_path
        except Exception:  # noqa: BLE001 - try the next, simpler variant
            continue
    shutil.copyfile(fp32_path, out_path)
    return out_path


class _Reader:
    def __init__(self, feeds: Sequence[dict[str, np.ndarray]]) -> None:
        self.feeds = list(feeds)
        self.i = 0

    def get_next(self):
        if self.i >= len(self.feeds):
            return None
        self.i += 1
        return self.feeds[self.i - 1]

    def rewind(self) -> None:
        self.i = 0


def _nodes_excluded(model: onnx.ModelProto, recipe: QuantRecipe,
                    extra_patterns: Sequence[str] = ()) -> list[str]:
    out = []
    pats = [re.compile(p) for p in (*recipe.exclude_name_patterns, *extra_patterns)]
    for node in model.graph.node:
        if node.op_type in recipe.exclude_op_types or any(p.search(node.name) for p in pats):
            out.append(node.name)
    return out


def quantize_int8(fp32_path: str | os.PathLike, int8_path: str | os.PathLike,
                  calibration_inputs: Sequence[dict[str, np.ndarray]], spec: ModelSpec | None,
                  options: QuantRecipe | None = None) -> Path:
    """Quantise an fp32 ONNX model to int8 with one recipe.

    ``quant_pre_process`` first, then static QDQ (per-channel by default) calibrated on
    ``calibration_inputs`` (list of feeds), or dynamic quantisation, per ``options``
    (default ``DEFAULT_RECIPES[0]``). The spec metadata is re-embedded.

    Nodes kept float: op types ``options.exclude_op_types``, names matching
    ``options.exclude_name_patterns`` or the kind's ``spec.extra["quant_float_patterns"]``
    (regular expressions on node names of the exported graph, e.g. attention internals).
    Note that onnxruntime fuses ``DQ -> op -> Q`` into an int8 kernel at load time when both
    neighbours are quantised, so keeping a region float means excluding its boundary nodes too.
    """
    from onnxruntime.quantization import QuantFormat, quantize_dynamic, quantize_static

    recipe = options or DEFAULT_RECIPES[0]
    int8_path = Path(int8_path)
    int8_path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=int8_path.parent) as td:
        pre = preprocess_model(fp32_path, Path(td) / "pre.onnx")
        model = onnx.load(str(pre))
        exclude = _nodes_excluded(model, recipe,
                                  (spec.extra.get("quant_float_patterns", ()) if spec else ()))
        extra = dict(recipe.extra_options)
        if recipe.mode in ("static", "static+dynamic"):
            if not calibration_inputs:
                raise ValueError("static quantisation needs calibration inputs")
            extra.setdefault("ActivationSymmetric", False)
            target = int8_path if recipe.mode == "static" else Path(td) / "static.onnx"
            quantize_static(
                str(pre), str(target), _Reader(calibration_inputs),
                quant_format=QuantFormat.QDQ, op_types_to_quantize=list(recipe.op_types) if recipe.op_types else None,
                per_channel=recipe.per_channel, reduce_range=recipe.reduce_range,
                activation_type=_qtype(recipe.activation_type), weight_type=_qtype(recipe.weight_type),
                nodes_to_exclude=exclude, calibrate_method=_calib_method(recipe.calibrate_method),
                extra_options=extra)
            if recipe.mode == "static+dynamic":
                quantize_dynamic(str(target), str(int8_path),
                                 op_types_to_quantize=list(recipe.dynamic_op_types),
                                 per_channel=recipe.per_channel, reduce_range=recipe.reduce_range,
                                 weight_type=_qtype(recipe.weight_type), nodes_to_exclude=exclude,
                                 extra_options=dict(recipe.extra_options))
        elif recipe.mode == "dynamic":
            quantize_dynamic(str(pre), str(int8_path),
                             op_types_to_quantize=list(recipe.dynamic_op_types),
                             per_channel=recipe.per_channel, reduce_range=recipe.reduce_range,
                             weight_type=_qtype(recipe.weight_type), nodes_to_exclude=exclude,
                             extra_options=extra)
        else:
            raise ValueError(f"unknown quantisation mode {recipe.mode!r}")
    if spec is not None:
        embed_spec(int8_path, spec, {"monodbh_quant_recipe": recipe.name})
    return int8_path


def metric_drop(fp32: float, other: float, higher_is_better: bool) -> float:
    """Relative loss of ``other`` vs ``fp32`` (positive = worse). Absolute when ``|fp32| < 1e-6``."""
    diff = (fp32 - other) if higher_is_better else (other - fp32)
    return float(diff / abs(fp32)) if abs(fp32) >= 1e-6 else float(diff)


def benchmark(fp32_path: str | os.PathLike, candidates: dict[str, str | os.PathLike],
              feeds: Sequence[dict[str, np.ndarray]], *,
              metric_fn: Callable[[Callable], dict[str, float]] | None = None,
              metric: str | None = None, higher_is_better: bool = True,
              tolerance: float = 0.03, max_rel_l2: float | None = None, n_runs: int = 20,
              warmup: int = 2, threads: int = 2,
              recipes: dict[str, str] | None = None) -> list[dict[str, Any]]:
    """Compare fp32 with int8 candidates: accuracy and latency, measured in the same run.

    Parameters
    ----------
    fp32_path : path
        Reference model (row ``"fp32"``).
    candidates : dict name -> path
        Quantised models.
    feeds : list of input dicts
        For the output relative L2 (mean over feeds of ``||q - f|| / ||f||``, max over outputs)
        and for latency (cycled).
    metric_fn : callable(predict) -> dict, optional
        Task metrics for a model; ``predict(feeds) -> {output: array}``. ``metric`` names the
        key compared (``drop`` = relative loss, see :func:`metric_drop`).
    tolerance : float
        A candidate passes when ``drop <= tolerance`` (task metric) and, if ``max_rel_l2`` is
        given, ``rel_l2 <= max_rel_l2``. Without ``metric_fn`` only the rel_l2 test applies
        (and ``max_rel_l2`` defaults to 0.05); the same 0.05 rel-L2 gate is used when the fp32
        task metric is ~0 (an untrained model: a relative drop means nothing).

    Returns
    -------
    list of dict
        One row per model with keys :data:`TABLE_COLUMNS` plus ``metrics`` (all task metrics)
        and ``rel_l2_per_output``.
    """
    names = ["fp32"] + list(candidates)
    paths = {"fp32": Path(fp32_path), **{k: Path(v) for k, v in candidates.items()}}
    sessions = {n: make_session(paths[n], threads=threads) for n in names}
    ref = [run_session(sessions["fp32"], f) for f in feeds]
    rows: dict[str, dict[str, Any]] = {}
    for n in names:
        per_out: dict[str, float] = {}
        if n != "fp32":
            for r, f in zip(ref, feeds):
                o = run_session(sessions[n], f)
                for k, v in r.items():
                    rel = float(np.linalg.norm(o[k] - v) / max(np.linalg.norm(v), 1e-12))
                    per_out[k] = per_out.get(k, 0.0) + rel / len(feeds)
        rows[n] = {"model": n, "recipe": (recipes or {}).get(n, "" if n != "fp32" else "-"),
                   "size_mb": paths[n].stat().st_size / 2**20,
                   "rel_l2": max(per_out.values()) if per_out else 0.0,
                   "rel_l2_per_output": per_out}
    # latency: models alternate in blocks (rounds), same feeds; blocks rather than single runs so
    # one session's spinning worker threads do not slow the next session's run
    times: dict[str, list[float]] = {n: [] for n in names}
    rounds = max(1, min(4, n_runs))
    per_round = [n_runs // rounds + (1 if r < n_runs % rounds else 0) for r in range(rounds)]
    k = 0
    for r in range(rounds):
        for n in names:
            for i in range(warmup + per_round[r]):
                f = feeds[(k + i) % len(feeds)]
                t0 = time.perf_counter()
                sessions[n].run(None, f)
                if i >= warmup:
                    times[n].append((time.perf_counter() - t0) * 1e3)
        k += per_round[r]
    for n in names:
        rows[n]["latency_ms"] = float(np.median(times[n]))
        rows[n]["latency_p90_ms"] = float(np.percentile(times[n], 90))
        rows[n]["speedup"] = rows["fp32"]["latency_ms"] / max(rows[n]["latency_ms"], 1e-9) \
            if rows["fp32"].get("latency_ms") else 1.0
    # task metric
    for n in names:
        if metric_fn is not None:
            sess = sessions[n]
            m = metric_fn(lambda feeds_, _s=sess: run_session(_s, feeds_))
            rows[n]["metrics"] = {k: float(v) for k, v in m.items()}
            rows[n]["metric"] = float(m[metric]) if metric else float("nan")
        else:
            rows[n]["metrics"] = {}
            rows[n]["metric"] = float("nan")
    lim_l2 = max_rel_l2 if max_rel_l2 is not None else (None if metric_fn else 0.05)
    if metric_fn is not None and metric and abs(rows["fp32"]["metric"]) < 1e-6 and lim_l2 is None:
        lim_l2 = 0.05  # degenerate fp32 metric (e.g. untrained model): gate on outputs instead
    for n in names:
        r = rows[n]
        if n == "fp32":
            r["drop"], r["pass"] = 0.0, True
            continue
        r["drop"] = (metric_drop(rows["fp32"]["metric"], r["metric"], higher_is_better)
                     if metric_fn is not None and metric else float("nan"))
        ok = True
        if metric_fn is not None and metric:
            ok = r["drop"] <= tolerance
        if lim_l2 is not None:
            ok = ok and r["rel_l2"] <= lim_l2
        r["pass"] = bool(ok)
    return [rows[n] for n in names]


def format_table(rows: Sequence[dict[str, Any]], metric_name: str = "metric") -> str:
    """Fixed-width text table of :func:`benchmark` rows (columns :data:`TABLE_COLUMNS`)."""
    head = [c if c != "metric" else metric_name for c in TABLE_COLUMNS]
    cells = []
    for r in rows:
        line = []
        for c in TABLE_COLUMNS:
            v = r.get(c, "")
            if isinstance(v, bool):
                line.append("yes" if v else "NO")
            elif isinstance(v, float):
                line.append(f"{v:.4f}" if c in ("rel_l2", "metric", "drop") else f"{v:.2f}")
            else:
                line.append(str(v))
        cells.append(line)
    widths = [max(len(h), *(len(l[i]) for l in cells)) for i, h in enumerate(head)]
    fmt = "  ".join("{:<%d}" % w for w in widths)
    out = [fmt.format(*head), fmt.format(*["-" * w for w in widths])]
    out += [fmt.format(*l) for l in cells]
    return "\n".join(out)


def search_int8(fp32_path: str | os.PathLike, int8_path: str | os.PathLike,
                calibration_inputs: Sequence[dict[str, np.ndarray]],
                eval_feeds: Sequence[dict[str, np.ndarray]], spec: ModelSpec, *,
                metric_fn: Callable[[Callable], dict[str, float]] | None = None,
                recipes: Sequence[QuantRecipe] = DEFAULT_RECIPES, tolerance: float = 0.03,
                max_rel_l2: float | None = None, exhaustive: bool = True, n_runs: int = 20,
                threads: int = 2, verbose: bool = True) -> dict[str, Any]:
    """Try ``recipes`` and write the best passing int8 model to ``int8_path``.

    Every recipe is quantised and measured against fp32 (``exhaustive=True``, keeps the fastest
    passing one) or recipes are tried in order until one passes (``exhaustive=False``). Recipes
    that fail to quantise or to run are reported with ``error``. If none passes, ``int8_path``
    is removed (never left stale) and ``chosen`` is ``None``.

    Returns
    -------
    dict
        ``{"chosen": recipe name or None, "rows": benchmark rows, "table": str,
        "errors": {recipe: message}, "tolerance": float}``.
    """
    int8_path = Path(int8_path)
    if int8_path.exists():
        int8_path.unlink()
    cand_dir = Path(tempfile.mkdtemp(dir=int8_path.parent, prefix=".int8_candidates_"))
    errors: dict[str, str] = {}
    rows: list[dict[str, Any]] = []
    chosen: str | None = None
    try:
        batches = [[r] for r in recipes] if not exhaustive else [list(recipes)]
        fp32_row = None
        by_name = {r.name: r for r in recipes}
        for batch in batches:
            cands: dict[str, Path] = {}
            for rec in batch:
                p = cand_dir / f"{rec.name}.onnx"
                try:
                    quantize_int8(fp32_path, p, calibration_inputs, spec, rec)
                    make_session(p, threads=threads)  # loads?
                    cands[rec.name] = p
                except Exception as e:  # noqa: BLE001 - report and try the next recipe
                    errors[rec.name] = f"{type(e).__name__}: {e}"[:500]
            if not cands:
                continue
            try:
                res = benchmark(fp32_path, cands, eval_feeds, metric_fn=metric_fn,
                                metric=spec.metric if metric_fn else None,
                                higher_is_better=spec.higher_is_better, tolerance=tolerance,
                                max_rel_l2=max_rel_l2, n_runs=n_runs, threads=threads,
                                recipes={k: k for k in cands})
            except Exception as e:  # noqa: BLE001
                for k in cands:
                    errors[k] = f"{type(e).__name__}: {e}"[:500]
                continue
            if fp32_row is None:
                fp32_row = res[0]
                rows.append(fp32_row)
            rows += res[1:]
            passing = [r for r in res[1:] if r["pass"]]
            if passing:
                best = min(passing, key=lambda r: (r["latency_ms"], r["drop"]))
                chosen = best["model"]
                if not exhaustive:
                    break
        if exhaustive and rows:
            passing = [r for r in rows[1:] if r["pass"]]
            chosen = min(passing, key=lambda r: (r["latency_ms"], r["drop"]))["model"] if passing else None
        if chosen is not None:
            shutil.copyfile(cand_dir / f"{chosen}.onnx", int8_path)
            for r in rows:
                r["chosen"] = r["model"] == chosen
    finally:
        shutil.rmtree(cand_dir, ignore_errors=True)
    table = format_table(rows, spec.metric) if rows else "(no candidate could be measured)"
    if verbose:
        print(table)
        for k, v in errors.items():
            print(f"recipe {k} failed: {v}")
        print(f"chosen int8 recipe: {chosen}" if chosen else
              f"no int8 recipe within tolerance {tolerance:.1%}: int8 model not written")
    return {"chosen": chosen, "recipe": by_name[chosen].to_dict() if chosen else None,
            "rows": rows, "table": table, "errors": errors, "tolerance": tolerance}
