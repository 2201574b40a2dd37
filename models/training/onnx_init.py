"""Warm start a training run from a shipped (int8 or fp32) ONNX model (training-only).

The shipped ``models/{kind}_int8.onnx`` is the only trained state that survives from one
working session to the next (runs and checkpoints are not committed), so training continues
from it: ``dbh train KIND --init models/KIND_int8.onnx``.

How the weights are recovered (:func:`state_dict_from_onnx`)
-----------------------------------------------------------
1. A fresh model of the same kind and size is exported with the project's own exporter
   (:func:`monodbh.models.export.onnx_io.export_onnx`), after its BatchNorm parameters and
   statistics were set to random values. The legacy exporter names initialisers
   deterministically, so this *probe* export has the same initialiser names as the shipped
   file had before quantisation (``onnx::Conv_121`` and so on).
2. Every probe initialiser is matched, by value, to the torch tensor(s) it came from:
   the tensor itself (``name == key``), its transpose (``nn.Linear`` weights as ``MatMul``
   inputs), a convolution folded with the following BatchNorm (weight scaled per output
   channel by ``gamma / sqrt(var + eps)``, bias ``beta - mean * gamma / sqrt(var + eps)``),
   or gathered pieces of one tensor (Swin's relative-position tables, embedding rows). The
   random BatchNorm values make each fold identifiable.
3. The shipped file's initialiser of the same name is read back to float (int8 weights are
   dequantised: ``(q - zero_point) * scale``, per channel where the scale is a vector) and
   put into the torch tensor through the inverse transform. A folded conv keeps the folded
   weight, and its BatchNorm is set to an affine identity plus the folded bias; it is then
   kept in eval mode while training (:func:`freeze_bn`).
4. Tensors the file holds only inside folded constants (the segmenter's learned queries and
   first query projection) are fitted to the file's outputs (:func:`fit_missing`).

Measured on the shipped int8 files, with a few training inputs as feeds: the recovered fp32
models reproduce their outputs to 0.19 % (CDEN), 4.1 % (segmenter, after the fit) and 9.4 %
(U-Net, mostly the file's own int8 error; 1.8 % from the true fp32 export) relative L2
(:func:`load_onnx_into` refuses more than 10 %, unless the file's own quantisation error is
that large: the shipped segmenter of 2026-12-01 is 14-17 % from its recovered weights, about as
far as their own re-quantised copy). Random inputs overstate this for static int8 files, which
saturate on them (24 % for the U-Net).
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

__all__ = ["read_onnx_weights", "state_dict_from_onnx", "load_onnx_into", "fidelity", "fit_missing", "freeze_bn",
           "quantization_floor"]


def read_onnx_weights(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """All initialisers of an ONNX file as float32 arrays, int8 weights dequantised.

    ``N_quantized`` / ``N_scale`` / ``N_zero_point`` triples (onnxruntime.quantization's
    naming) come back as ``N``; the per-channel axis is the ``DequantizeLinear`` node's
    ``axis`` attribute, else the one axis whose length matches the scale vector.

    Returns
    -------
    dict
        ``{name: (shape...) float32}`` (integer initialisers that are not quantised weights,
        e.g. shape constants, are returned as they are).
    """
    import onnx
    from onnx import numpy_helper

    m = onnx.load(str(path))
    raw = {i.name: numpy_helper.to_array(i) for i in m.graph.initializer}
    out: dict[str, np.ndarray] = {}
    consumed: set[str] = set()

    def deq(q, s, z, ax):
        q = q.astype(np.float32)
        s = np.asarray(s, np.float32)
        z = np.zeros_like(s) if z is None else np.asarray(z, np.float32)
        if s.size > 1:
            if ax is None:
                cands = [i for i, n in enumerate(q.shape) if n == s.size]
                ax = cands[0] if len(cands) == 1 else (0 if q.ndim == 4 else q.ndim - 1)
            shape = [1] * q.ndim
            shape[ax if ax >= 0 else q.ndim + ax] = s.size
            s, z = s.reshape(shape), z.reshape(shape)
        return ((q - z) * s).astype(np.float32)

    # static QDQ: every DequantizeLinear of an initialiser gives back the float weight; its name is
    # the node's output ("N") or the output less "_DequantizeLinear_Output"
    for node in m.graph.node:
        if node.op_type != "DequantizeLinear" or not node.input or node.input[0] not in raw:
            continue
        ins = list(node.input) + [""] * 3
        if ins[1] not in raw:
            continue
        ax = next((int(a.i) for a in node.attribute if a.name == "axis"), None)
        name = node.output[0]
        if name.endswith("_DequantizeLinear_Output"):
            name = name[: -len("_DequantizeLinear_Output")]
        out[name] = deq(raw[ins[0]], raw[ins[1]], raw.get(ins[2]), ax)
        consumed.update(x for x in ins[:3] if x)
    # dynamic quantisation (MatMulInteger etc.): N_quantized / N_scale / N_zero_point
    for name, arr in raw.items():
        if name in consumed or not name.endswith("_quantized"):
            continue
        base = name[: -len("_quantized")]
        if base + "_scale" in raw:
            out.setdefault(base, deq(arr, raw[base + "_scale"], raw.get(base + "_zero_point"), None))
            consumed.update({name, base + "_scale", base + "_zero_point"})
    for name, arr in raw.items():
        if name not in consumed and name not in out:
            out[name] = arr.astype(np.float32) if arr.dtype.kind == "f" else arr
    return out


def _randomise(model: nn.Module, seed: int = 12345) -> dict[str, nn.modules.batchnorm._BatchNorm]:
    """Give every parameter distinct random values (the exporter merges equal initialisers, e.g.
    the all-ones weights of fresh LayerNorms) and BatchNorm random statistics (folds identifiable)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(torch.randn(p.shape, generator=g) * 0.02)
    bns = {}
    for name, mod in model.named_modules():
        if isinstance(mod, nn.modules.batchnorm._BatchNorm):
            c = mod.num_features
            with torch.no_grad():
                mod.running_mean.copy_(torch.randn(c, generator=g) * 0.3)
                mod.running_var.copy_(torch.rand(c, generator=g) * 2.0 + 0.5)
                if mod.affine:
                    mod.weight.copy_(torch.rand(c, generator=g) * 1.5 + 0.5)
                    mod.bias.copy_(torch.randn(c, generator=g) * 0.3)
            bns[name] = mod
    return bns


def _close(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and np.allclose(a, b, rtol=1e-4, atol=1e-6)


def _node_values(path: Path, names: list[str], spec) -> dict[str, np.ndarray]:
    """Values of intermediate tensors ``names`` of the ONNX graph at ``path`` (constant
    subgraphs: any input gives them), for those that are node outputs there."""
    import onnx
    import onnxruntime as ort

    from monodbh.models.export.onnx_io import random_feeds

    m = onnx.load(str(path))
    produced = {o for n in m.graph.node for o in n.output}
    want = [n for n in names if n in produced]
    if not want:
        return {}
    have = {o.name for o in m.graph.output}
    for n in want:
        if n not in have:
            m.graph.output.append(onnx.ValueInfoProto(name=n))
    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    sess = ort.InferenceSession(m.SerializeToString(), so, providers=["CPUExecutionProvider"])
    vals = sess.run(want, random_feeds(spec, seed=0))
    return {n: np.asarray(v) for n, v in zip(want, vals) if np.asarray(v).dtype.kind == "f"}


def _probe(model: nn.Module, extra_names: list[str] | None = None):
    """Export the (BN-randomised) model; return ``(probe, mapping, gathers, reps)``: the probe
    initialisers, a map ``onnx_name -> (kind, torch_key, extra)`` with kind in ``same |
    transpose | fold_w | fold_b | gather``, for gathers the flat torch indices of each onnx
    element, and per gathered torch key the index of each element's first equal value. ``extra_names``: tensors that are initialisers in the target file but node
    outputs in the probe (constant branches folded by onnxruntime's optimiser); their probe
    values are computed and matched too."""
    from monodbh.models.export.onnx_io import export_onnx

    with tempfile.TemporaryDirectory() as td:
        p = Path(td) / "probe.onnx"
        export_onnx(model, model.spec, p, check=False)
        probe = read_onnx_weights(p)
        if extra_names:
            probe.update({k: v for k, v in _node_values(p, [n for n in extra_names if n not in probe],
                                                        model.spec).items()})
    sd = {k: v.detach().cpu().numpy() for k, v in model.state_dict().items()
          if v.is_floating_point()}
    mapping: dict[str, tuple[str, str, str]] = {}
    used: set[str] = set()
    gathers: dict[str, np.ndarray] = {}
    reps: dict[str, np.ndarray] = {}
    # 1. same name, same value
    for name, arr in probe.items():
        if name in sd and _close(arr, sd[name]):
            mapping[name] = ("same", name, "")
            used.add(name)
    # conv -> bn pairs by module order (a BN follows the conv whose out channels it normalises)
    mods = dict(model.named_modules())
    convs = [(n, m) for n, m in mods.items() if isinstance(m, (nn.Conv2d, nn.Conv1d, nn.Linear))]
    bns = [(n, m) for n, m in mods.items() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
    folds: dict[tuple[str, str], tuple[np.ndarray, np.ndarray, str, str]] = {}
    for bn_name, bn in bns:
        scale = (bn.weight / torch.sqrt(bn.running_var + bn.eps)).detach().numpy()
        shift = (bn.bias - bn.running_mean * bn.weight / torch.sqrt(bn.running_var + bn.eps)).detach().numpy()
        for conv_name, conv in convs:
            w = conv.weight.detach().numpy()
            if w.shape[0] != bn.num_features:
                continue
            fw = w * scale.reshape((-1,) + (1,) * (w.ndim - 1))
            fb = shift + (conv.bias.detach().numpy() * scale if conv.bias is not None else 0.0)
            folds[(conv_name, bn_name)] = (fw, fb, conv_name + ".weight", bn_name)
    by_shape: dict[tuple, list[str]] = {}
    for k, v in sd.items():
        by_shape.setdefault(tuple(v.shape), []).append(k)
    for name, arr in probe.items():
        if name in mapping or arr.dtype.kind != "f" or arr.ndim == 0:
            continue
        hit = None
        if arr.ndim == 2:
            for k in by_shape.get(tuple(arr.shape[::-1]), []):
                if k not in used and _close(arr, sd[k].T):
                    hit = ("transpose", k, "")
                    break
        if hit is None:
            for k in by_shape.get(tuple(arr.shape), []):
                if k not in used and _close(arr, sd[k]):
                    hit = ("same", k, "")
                    break
        if hit is None and arr.ndim >= 2:
            for (fw, fb, wkey, bn_name) in folds.values():
                if _close(arr, fw):
                    hit = ("fold_w", wkey, bn_name)
                    break
        if hit is None and arr.ndim == 1:
            for (fw, fb, wkey, bn_name) in folds.values():
                if _close(arr, fb):
                    hit = ("fold_b", wkey, bn_name)
                    break
        if hit is not None:
            mapping[name] = hit
            used.add(hit[1])
    # 3. gathered copies (e.g. Swin's relative-position bias table indexed and constant-folded,
    # rows of an embedding picked by a constant index): every value of the initialiser found,
    # exactly, in one unused torch tensor; the pieces of one tensor must cover all of it
    pieces: dict[str, list[str]] = {}
    for name, arr in probe.items():
        if name in mapping or arr.dtype.kind != "f" or arr.size < 2:
            continue
        for k, v in sd.items():
            if k in used or v.size < 2:
                continue
            flat = v.ravel()
            order = np.argsort(flat, kind="stable")
            pos = np.clip(np.searchsorted(flat[order], arr.ravel()), 0, flat.size - 1)
            idx = order[pos]
            if np.array_equal(flat[idx], arr.ravel()):
                gathers[name] = idx.reshape(arr.shape)
                pieces.setdefault(k, []).append(name)
                break
    for k, names in pieces.items():
        # equal values (rare float collisions) all map to their first index: compare on those
        flat = sd[k].ravel()
        order = np.argsort(flat, kind="stable")
        rep = order[np.searchsorted(flat[order], flat)]
        reps[k] = rep
        covered = np.unique(np.concatenate([gathers[n].ravel() for n in names]))
        if np.isin(np.unique(rep), covered).all():
            for n in names:
                mapping[n] = ("gather", k, "")
    return probe, mapping, gathers, reps


def state_dict_from_onnx(onnx_path: str | os.PathLike, model: nn.Module) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Recover ``model``'s state dict from an exported (int8 or fp32) ONNX file of the same kind/size.

    Parameters
    ----------
    onnx_path : path
        ``models/{kind}_int8.onnx`` (or an fp32 export).
    model : nn.Module
        A freshly built model of the same kind and size (``registry.build``), with ``.spec``.
        Its BatchNorm values are overwritten by the probe export; load the returned dict.

    Returns
    -------
    (state_dict, info)
        ``info``: ``{"matched": n, "missing": [torch keys not recovered], "folded_bn": [names]}``.
        Raises ``ValueError`` when the file does not fit the model (shapes or names differ).
    """
    model = model.cpu().eval()
    _randomise(model)
    shipped = read_onnx_weights(onnx_path)
    probe, mapping, gathers, reps = _probe(model, [n for n, a in shipped.items() if a.dtype.kind == "f"])
    sd = {k: v.clone() for k, v in model.state_dict().items()}
    float_keys = {k for k, v in sd.items() if v.is_floating_point()}
    set_keys: set[str] = set()
    folded: dict[str, dict[str, np.ndarray]] = {}
    bad, absent = [], []
    gather_acc: dict[str, list[np.ndarray]] = {}
    for name, (how, key, extra) in mapping.items():
        if name not in shipped:      # folded away in the shipped file (e.g. a constant branch)
            absent.append(name)
            continue
        arr = shipped[name]
        if how == "transpose":
            arr = arr.T
        if how == "gather":
            acc_n = gather_acc.setdefault(key, [np.zeros(sd[key].numel()), np.zeros(sd[key].numel())])
            idx = gathers[name].ravel()
            acc_n[0] += np.bincount(idx, weights=arr.ravel().astype(np.float64), minlength=acc_n[0].size)
            acc_n[1] += np.bincount(idx, minlength=acc_n[0].size)
            continue
        if how in ("same", "transpose", "fold_w"):
            if tuple(arr.shape) != tuple(sd[key].shape):
                bad.append(name)
                continue
            sd[key] = torch.from_numpy(np.ascontiguousarray(arr)).to(sd[key].dtype)
            set_keys.add(key)
        if how in ("fold_w", "fold_b"):
            folded.setdefault(extra, {})["conv"] = key
            if how == "fold_b":
                folded[extra]["bias"] = arr
    for key, (acc, cnt) in gather_acc.items():
        rep = reps[key]
        acc, cnt = acc[rep], cnt[rep]
        if cnt.min() > 0:                 # every element seen (pieces may be folded away)
            sd[key] = torch.from_numpy((acc / cnt).astype(np.float32)).reshape(sd[key].shape)
            set_keys.add(key)
    if bad:
        raise ValueError(f"{onnx_path}: {len(bad)} weights do not fit a fresh {getattr(model, 'kind', '?')}/"
                         f"{getattr(model, 'size', '?')} model (e.g. {bad[:3]})")
    bn_names = []
    for bn_name, f in folded.items():
        conv_key = f["conv"]
        bias = f.get("bias")
        conv_bias_key = conv_key[: -len("weight")] + "bias"
        if conv_bias_key in sd:           # the fold absorbed the conv bias: keep it zero
            sd[conv_bias_key] = torch.zeros_like(sd[conv_bias_key])
            set_keys.add(conv_bias_key)
        c = sd[bn_name + ".running_mean"].numel()
        eps = dict(model.named_modules())[bn_name].eps
        sd[bn_name + ".running_mean"] = torch.zeros(c)
        sd[bn_name + ".running_var"] = torch.full((c,), 1.0 - eps)
        if bn_name + ".weight" in sd:
            sd[bn_name + ".weight"] = torch.ones(c)
            sd[bn_name + ".bias"] = torch.from_numpy(bias.copy()) if bias is not None else torch.zeros(c)
        for s in ("running_mean", "running_var", "weight", "bias"):
            set_keys.add(f"{bn_name}.{s}")
        bn_names.append(bn_name)
    missing = sorted(k for k in float_keys - set_keys)
    return sd, {"matched": len(set_keys), "missing": missing, "folded_bn": bn_names, "absent": absent,
                "n_float_keys": len(float_keys)}


def fidelity(model: nn.Module, onnx_path: str | os.PathLike, feeds: list[dict[str, np.ndarray]] | None = None) -> float:
    """Worst relative L2 error ``|torch - ort| / |ort|`` over the outputs, on ``feeds``
    (default: two random feeds from the spec). ``model`` in eval mode."""
    from monodbh.models.export.onnx_io import make_session, random_feeds, run_session

    spec = model.spec
    feeds = feeds or [random_feeds(spec, seed=7), random_feeds(spec, seed=8)]
    sess = make_session(onnx_path)
    was = model.training
    model.eval()
    worst = 0.0
    with torch.no_grad():
        for f in feeds:
            ref = run_session(sess, f)
            out = model(*[torch.from_numpy(f[n]) for n in spec.input_names])
            out = out if isinstance(out, (tuple, list)) else (out,)
            for name, o in zip(spec.output_names, out):
                r = np.asarray(ref[name], np.float64)
                worst = max(worst, float(np.linalg.norm(o.numpy().astype(np.float64) - r)
                                         / max(np.linalg.norm(r), 1e-12)))
    model.train(was)
    return worst


def fit_missing(model: nn.Module, onnx_path: str | os.PathLike, keys: list[str],
                feeds: list[dict[str, np.ndarray]], steps: int = 300, lr: float = 3e-2) -> float:
    """Fit the parameters ``keys`` (the rest frozen) so that ``model`` reproduces the ONNX file's
    outputs on ``feeds`` (Adam on the variance-normalised squared error; eval mode).

    For tensors whose values the file no longer holds as such, e.g. learned queries and the
    first query projection of a decoder, which the optimiser folded into constants. Returns
    the final loss.
    """
    from monodbh.models.export.onnx_io import make_session, run_session

    spec = model.spec
    sess = make_session(onnx_path)
    refs = [run_session(sess, f) for f in feeds]
    params = dict(model.named_parameters())
    train = [params[k] for k in keys if k in params]
    if not train:
        return 0.0
    flags = {n: p.requires_grad for n, p in params.items()}
    for n, p in params.items():
        p.requires_grad_(n in keys)
    opt = torch.optim.Adam(train, lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    was = model.training
    model.eval()
    loss_v = 0.0
    try:
        for it in range(steps):
            f, ref = feeds[it % len(feeds)], refs[it % len(feeds)]
            out = model(*[torch.from_numpy(f[n]) for n in spec.input_names])
            out = out if isinstance(out, (tuple, list)) else (out,)
            loss = 0.0
            for name, o in zip(spec.output_names, out):
                r = torch.from_numpy(np.asarray(ref[name], np.float32))
                loss = loss + ((o - r) ** 2).mean() / (r.var() + 1e-8)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            loss_v = float(loss)
    finally:
        for n, p in params.items():
            p.requires_grad_(flags[n])
        model.train(was)
    return loss_v


def freeze_bn(model: nn.Module) -> int:
    """Keep every BatchNorm of ``model`` in eval mode (running statistics, affine trainable)
    whatever ``model.train()`` says: the fine-tuning regime of a network whose BatchNorms were
    folded into its convolutions at export (loaded back as identity + bias). Returns the count."""
    n = 0
    for m in model.modules():
        if isinstance(m, nn.modules.batchnorm._BatchNorm):
            m.eval()
            m.train = _stay_eval.__get__(m)          # Module.train() recurses through children
            n += 1
    return n


def _stay_eval(self, mode: bool = True):
    nn.Module.train(self, False)
    return self


def _is_quantized(onnx_path: str | os.PathLike) -> bool:
    """Whether the file holds int8 QDQ or dynamically quantised nodes."""
    import onnx
    ops = {n.op_type for n in onnx.load(str(onnx_path), load_external_data=False).graph.node}
    return bool(ops & {"QuantizeLinear", "DequantizeLinear", "DynamicQuantizeLinear", "MatMulInteger",
                       "ConvInteger"})


def _file_recipe(onnx_path: str | os.PathLike):
    """The quantisation recipe the file was made with (its manifest entry's ``quant_recipe``
    where a ``manifest.json`` beside it lists it, else the export's first default recipe)."""
    from monodbh.models.export.quantize import DEFAULT_RECIPES
    from monodbh.models.runtime.common import MonodbhError, load_manifest
    path = Path(onnx_path)
    try:
        entries = load_manifest(path.parent / "manifest.json")["models"].values()
    except MonodbhError:
        entries = []
    name = next((e.get("quant_recipe") for e in entries if isinstance(e, dict) and e.get("file") == path.name), None)
    return next((r for r in DEFAULT_RECIPES if r.name == name), DEFAULT_RECIPES[0])


def quantization_floor(model: nn.Module, onnx_path: str | os.PathLike, feeds: list[dict[str, np.ndarray]],
                       calib_feeds: list[dict[str, np.ndarray]] | None = None) -> float:
    """How far an int8 file of ``model`` itself is from ``model`` on ``feeds`` (:func:`fidelity`):
    the model exported to fp32 and quantised again with ``onnx_path``'s recipe, calibrated on
    ``calib_feeds`` (default ``feeds``; calibrating on the compared inputs themselves
    understates the floor, so other inputs, as many as the export uses, are better).

    An int8 file cannot be reproduced by any float model closer than its own quantisation error;
    the recovered weights of such a file are as right as they can be when they reproduce it about
    as well as their own re-quantised copy does."""
    from monodbh.models.export.onnx_io import export_onnx
    from monodbh.models.export.quantize import quantize_int8
    with tempfile.TemporaryDirectory() as tmp:
        fp32, int8 = Path(tmp) / "fp32.onnx", Path(tmp) / "int8.onnx"
        export_onnx(model, model.spec, fp32, check=False)
        quantize_int8(fp32, int8, calib_feeds or feeds, model.spec, _file_recipe(onnx_path))
        return fidelity(model, int8, feeds)


def load_onnx_into(model: nn.Module, onnx_path: str | os.PathLike, max_rel_l2: float = 0.1,
                   feeds: list[dict[str, np.ndarray]] | None = None, fit_steps: int = 300,
                   floor_factor: float = 2.0,
                   calib_feeds: list[dict[str, np.ndarray]] | None = None) -> dict[str, Any]:
    """Load ``onnx_path``'s weights into ``model`` in place (see :func:`state_dict_from_onnx`)
    and check that the torch model now computes what the ONNX file computes.

    Tensors the file has no trace of (e.g. the norms of encoder levels the decoder never reads,
    pruned by the exporter) keep their fresh values and are listed in ``info["missing"]``. When
    the outputs then differ by more than ``max_rel_l2 / 2``, the missing parameters are fitted to
    the file's outputs on ``feeds`` (:func:`fit_missing`; kept only where it brings them closer).
    When they still differ by more than
    ``max_rel_l2`` and the file is quantised, the recovered model is accepted within
    ``floor_factor`` times its own re-quantised copy's difference (:func:`quantization_floor`,
    calibrated on ``calib_feeds``; ``info["quant_floor"]``): the shipped segmenter differs from
    its recovered weights by 14 %, and from their copy re-quantised on 32 other training inputs
    by 16 %. Raises ``ValueError`` otherwise.
    """
    import copy

    from monodbh.models.export.onnx_io import random_feeds

    work = copy.deepcopy(model).cpu()          # the probe export and the checks run on the CPU
    work.spec = model.spec
    sd, info = state_dict_from_onnx(onnx_path, copy.deepcopy(work))
    work.load_state_dict(sd)
    feeds = feeds or [random_feeds(model.spec, seed=s) for s in range(7, 11)]
    info["rel_l2_loaded"] = info["rel_l2"] = fidelity(work, onnx_path, feeds)
    if info["rel_l2"] > max_rel_l2 / 2 and info["missing"] and fit_steps:
        before = copy.deepcopy(work.state_dict())
        info["fit_loss"] = fit_missing(work, onnx_path, info["missing"], feeds, steps=fit_steps)
        rel = fidelity(work, onnx_path, feeds)
        if rel < info["rel_l2"]:
            info["rel_l2"] = rel
        else:                                   # the fit did not help (e.g. the gap is the file's int8 error)
            work.load_state_dict(before)
            info["fit_kept"] = False
    model.load_state_dict(work.state_dict())
    limit = max_rel_l2
    if not info["rel_l2"] <= max_rel_l2 and _is_quantized(onnx_path):
        info["quant_floor"] = quantization_floor(work, onnx_path, feeds, calib_feeds)
        limit = max(max_rel_l2, floor_factor * info["quant_floor"])
    if not info["rel_l2"] <= limit:
        floor = (f"; its own re-quantised copy differs by {info['quant_floor']:.1%}"
                 if "quant_floor" in info else "")
        raise ValueError(f"{onnx_path}: recovered weights reproduce the file's outputs only to "
                         f"{info['rel_l2']:.1%} relative L2 (limit {max_rel_l2:.0%}{floor}); "
                         f"unrecovered: {info['missing'][:4]}")
    return info
