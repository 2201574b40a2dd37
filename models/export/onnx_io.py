"""fp32 ONNX export of a registered model and the torch-vs-onnxruntime equality check."""
from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime as ort
import torch

from monodbh.models.modeling.registry import ModelSpec

__all__ = ["SPEC_METADATA_KEY", "export_onnx", "check_onnx_matches_torch", "make_session",
           "random_feeds", "read_spec", "run_session"]

#: ONNX metadata key holding ``ModelSpec.to_json()`` (read by ``monodbh.models.runtime``).
SPEC_METADATA_KEY = "monodbh_spec"


def random_feeds(spec: ModelSpec, seed: int = 0) -> dict[str, np.ndarray]:
    """Standard-normal float32 inputs of the spec's shapes (dummy export / latency inputs)."""
    rng = np.random.default_rng(seed)
    return {t.name: rng.standard_normal(t.shape).astype(t.dtype) for t in spec.inputs}


def make_session(path: str | os.PathLike, threads: int = 2,
                 optimize: bool = True) -> ort.InferenceSession:
    """CPU onnxruntime session with ``threads`` intra-op threads (1 inter-op thread)."""
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = (ort.GraphOptimizationLevel.ORT_ENABLE_ALL if optimize
                                   else ort.GraphOptimizationLevel.ORT_DISABLE_ALL)
    so.log_severity_level = 3
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def run_session(sess: ort.InferenceSession, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Run and return ``{output name: array}``."""
    names = [o.name for o in sess.get_outputs()]
    return dict(zip(names, sess.run(names, feeds)))


def read_spec(path: str | os.PathLike) -> ModelSpec:
    """The :class:`ModelSpec` embedded in an exported ONNX file."""
    m = onnx.load(str(path), load_external_data=False)
    for p in m.metadata_props:
        if p.key == SPEC_METADATA_KEY:
            return ModelSpec.from_dict(json.loads(p.value))
    raise KeyError(f"{path}: no {SPEC_METADATA_KEY} metadata")


def _set_metadata(model: onnx.ModelProto, spec: ModelSpec, extra: dict[str, str] | None) -> None:
    props = {p.key: p.value for p in model.metadata_props}
    props[SPEC_METADATA_KEY] = spec.to_json()
    props.update(extra or {})
    del model.metadata_props[:]
    for k, v in props.items():
        e = model.metadata_props.add()
        e.key, e.value = k, v


def embed_spec(path: str | os.PathLike, spec: ModelSpec,
               extra: dict[str, str] | None = None) -> None:
    """(Re-)write the spec metadata into an ONNX file in place (quantisation drops it)."""
    m = onnx.load(str(path))
    _set_metadata(m, spec, extra)
    onnx.save(m, str(path))


def export_onnx(model: torch.nn.Module, spec: ModelSpec, path: str | os.PathLike, *,
                check: bool = True, atol: float = 1e-4, rtol: float = 1e-3,
                metadata: dict[str, str] | None = None) -> dict[str, Any]:
    """Export ``model`` (eval mode, batch 1, fixed shapes) to fp32 ONNX with the spec embedded.

    Parameters
    ----------
    model : nn.Module
        ``forward(*inputs)`` in spec input order, returning a tensor or tuple in output order.
    spec : ModelSpec
        Names, shapes and opset; stored as JSON under metadata key ``monodbh_spec``.
    path : path
        Output ``.onnx`` file.
    check : bool
        Run :func:`check_onnx_matches_torch` and raise ``AssertionError`` on mismatch.

    Returns
    -------
    dict
        ``{"path", "max_abs_err": {output: float}, "max_rel_err": {...}}`` (errors only if checked).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    was_training = model.training
    model.eval()
    feeds = random_feeds(spec, seed=0)
    args = tuple(torch.from_numpy(feeds[n]) for n in spec.input_names)
    tmp = path.with_suffix(".tmp.onnx")
    with torch.no_grad(), warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)
        torch.onnx.export(model, args, str(tmp), input_names=spec.input_names,
                          output_names=spec.output_names, opset_version=spec.opset,
                          dynamo=False, do_constant_folding=True)
    m = onnx.load(str(tmp))
    _set_metadata(m, spec, metadata)
    onnx.checker.check_model(m)
    onnx.save(m, str(path))
    tmp.unlink()
    out: dict[str, Any] = {"path": str(path)}
    if check:
        out.update(check_onnx_matches_torch(model, spec, path, atol=atol, rtol=rtol))
    model.train(was_training)
    return out


def check_onnx_matches_torch(model: torch.nn.Module, spec: ModelSpec, path: str | os.PathLike,
                             feeds: list[dict[str, np.ndarray]] | None = None,
                             atol: float = 1e-4, rtol: float = 1e-3,
                             raise_on_fail: bool = True) -> dict[str, Any]:
    """Compare onnxruntime (no graph optimisation off: default ALL) with torch on ``feeds``.

    Passes when, for every output, ``max|ort - torch| <= atol + rtol * max|torch|``.

    Returns
    -------
    dict
        ``{"max_abs_err": {name: float}, "max_rel_err": {name: float}, "ok": bool}``.
    """
    model.eval()
    feeds = feeds or [random_feeds(spec, seed=1), random_feeds(spec, seed=2)]
    sess = make_session(path)
    abs_err: dict[str, float] = {n: 0.0 for n in spec.output_names}
    rel_err: dict[str, float] = {n: 0.0 for n in spec.output_names}
    ok = True
    for f in feeds:
        with torch.no_grad():
            t = model(*[torch.from_numpy(f[n]) for n in spec.input_names])
        t = (t,) if isinstance(t, torch.Tensor) else tuple(t)
        o = run_session(sess, f)
        for name, tt in zip(spec.output_names, t):
            tt = tt.numpy()
            oo = o[name]
            if oo.shape != tt.shape:
                raise AssertionError(f"{path}: output {name} shape {oo.shape} != torch {tt.shape}")
            err = float(np.abs(oo - tt).max())
            scale = float(np.abs(tt).max())
            abs_err[name] = max(abs_err[name], err)
            rel_err[name] = max(rel_err[name], err / max(scale, 1e-12))
            if err > atol + rtol * scale:
                ok = False
    res = {"max_abs_err": abs_err, "max_rel_err": rel_err, "ok": ok}
    if raise_on_fail and not ok:
        raise AssertionError(f"{path}: onnxruntime differs from torch: {res}")
    return res
