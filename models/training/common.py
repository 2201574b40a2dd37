"""Shared training harness for all network kinds (segmenter, depth, tree, stem_base, rope_verifier, rope_finder).

What is here
------------
* Reproducibility: :func:`seed_everything`, :func:`rng_state` / :func:`set_rng_state`,
  :func:`select_device`.
* Run folder (:class:`RunDir`)::

      RUN_DIR/config.json     kind, size, seed, steps, batch_size, hyper-parameters, data config
      RUN_DIR/checkpoint.pt   latest {"model", "optim", "scheduler", "extra", "step", "rng", ...}
                              written atomically (tmp + os.replace) every N steps and at the end
      RUN_DIR/log.jsonl       one JSON object per line: {"step", "kind": "train"|"val", ...}
      RUN_DIR/export/         written by ``dbh export`` (monodbh.models.export)

* :func:`train_loop`: the generic loop (resume, periodic logging/validation/checkpointing). A kind
  supplies ``step_fn(step) -> dict of floats`` (does forward, backward, optimiser step) and
  ``validate_fn() -> dict of floats``. Data are a pure function of ``(seed, step)``
  (:func:`batch_indices`, :func:`sample_rng`), and the torch/numpy/python RNG states are saved in
  the checkpoint, so ``resume=True`` continues exactly as an uninterrupted run would.
* Data sources (:class:`DataSource`): :class:`FolderSource` (``dbh synth`` folders),
  :class:`GeneratorSource` (on the fly from ``monodbh.models.synthetic.iter_samples``),
  :class:`ListSource` (in-memory dicts, tests); :func:`make_source` builds one from a CLI-ish
  value and :meth:`DataSource.config` / :func:`source_from_config` round-trip through config.json.
* Augmentation (numpy/cv2, on sample dicts, for all kinds): :class:`AugmentConfig`,
  :func:`photometric`, :func:`geometric`, :func:`augment`, :func:`resize_sample`.
* Per-kind export hooks: :func:`register_calibration` / :func:`calibration_inputs` and
  :func:`register_eval` / :func:`evaluate_kind` (used by ``monodbh.models.export``).

Sample dicts are those of the synthetic format (docs/ARCHITECTURE.md): ``rgb`` (H, W, 3) uint8,
``depth``, ``semantic``, ``instance``, ``rope``, ``z1``, ``z2`` (H, W) and ``meta`` (JSON record).
"""
from __future__ import annotations

import importlib
import json
import os
import random
import tempfile
from collections import OrderedDict
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import cv2
import numpy as np
import torch

__all__ = [
    "seed_everything", "rng_state", "set_rng_state", "select_device", "RunDir", "train_loop",
    "batch_indices", "sample_rng", "DataSource", "BankSource", "FolderSource", "GeneratorSource", "ListSource",
    "make_source", "source_from_config", "config_from_dict", "AugmentConfig", "AUGMENT_PRESETS", "photometric", "geometric", "augment",
    "resize_sample", "SPATIAL_KEYS", "TRAINING_MODULES", "register_calibration",
    "calibration_inputs", "register_eval", "evaluate_kind", "load_run_model", "atomic_torch_save", "pack_weights", "load_packed_weights",
    "atomic_write_text", "warmup_cosine", "binary_auc", "bank_source", "bank_run_sources",
    "resumed_folder_run", "held_out_split", "held_out_bank",
]

# --------------------------------------------------------------------------- reproducibility


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch (CPU and CUDA) RNGs."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    if torch.cuda.is_available():
        torch.cuda.manual_seed_all(seed)


def rng_state() -> dict[str, Any]:
    """Snapshot of python, numpy, torch (and CUDA) RNG states, for checkpoints."""
    state = {"python": random.getstate(), "numpy": np.random.get_state(),
             "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore a :func:`rng_state` snapshot."""
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def select_device(threads: int | None = None) -> torch.device:
    """CUDA if available, else CPU with ``torch.set_num_threads(threads or os.cpu_count())``."""
    if torch.cuda.is_available():
        return torch.device("cuda")
    torch.set_num_threads(threads or os.cpu_count() or 1)
    return torch.device("cpu")


# --------------------------------------------------------------------------- run folder


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` via a temporary file in the same folder and ``os.replace``."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_torch_save(obj: Any, path: str | os.PathLike) -> None:
    """``torch.save`` to a temporary file, fsync, then ``os.replace`` onto ``path``."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(obj, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


class RunDir:
    """Paths and I/O of one training run folder (layout in the module docstring)."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.config_path = self.path / "config.json"
        self.checkpoint_path = self.path / "checkpoint.pt"
        self.log_path = self.path / "log.jsonl"
        self.export_dir = self.path / "export"

    def mkdir(self) -> "RunDir":
        self.path.mkdir(parents=True, exist_ok=True)
        return self

    def write_config(self, config: dict[str, Any]) -> None:
        self.mkdir()
        atomic_write_text(self.config_path, json.dumps(config, indent=2, sort_keys=True) + "\n")

    def read_config(self) -> dict[str, Any]:
        return json.loads(self.config_path.read_text())

    def log(self, record: dict[str, Any]) -> None:
        """Append one JSON line (floats/ints/strings; numpy scalars converted)."""
        self.mkdir()
        with open(self.log_path, "a") as f:
            f.write(json.dumps(_jsonable(record), sort_keys=True) + "\n")
            f.flush()

    def read_log(self) -> list[dict[str, Any]]:
        if not self.log_path.exists():
            return []
        return [json.loads(l) for l in self.log_path.read_text().splitlines() if l.strip()]

    def truncate_log(self, after_step: int) -> None:
        """Drop log records with ``step > after_step`` (written after the last checkpoint)."""
        recs = [r for r in self.read_log() if int(r.get("step", 0)) <= after_step]
        atomic_write_text(self.log_path, "".join(json.dumps(r, sort_keys=True) + "\n" for r in recs))

    def save_checkpoint(self, state: dict[str, Any]) -> None:
        self.mkdir()
        atomic_torch_save(state, self.checkpoint_path)

    def load_checkpoint(self, map_location: str | torch.device = "cpu") -> dict[str, Any] | None:
        if not self.checkpoint_path.exists():
            return None
        return torch.load(self.checkpoint_path, map_location=map_location, weights_only=False)


def pack_weights(run_dir: str | os.PathLike, out: str | os.PathLike) -> dict[str, Any]:
    """Write the run's model weights only, as float16, to ``out`` (a small file to commit).

    Training continues from it on another machine with ``dbh train KIND --init OUT`` (fresh
    optimiser). Returns ``{"kind", "size", "step", "bytes"}``.
    """
    run = RunDir(run_dir)
    ckpt = run.load_checkpoint()
    if ckpt is None:
        raise FileNotFoundError(f"{run.checkpoint_path}: no checkpoint")
    sd = {k: (v.half() if v.is_floating_point() else v) for k, v in ckpt["model"].items()}
    # "step" counts every step behind these weights: the run's own plus those of the weights it
    # was itself started from (so total_steps in the manifest stays right across packs)
    cfg = ckpt.get("config") or {}
    if not cfg and (Path(run_dir) / "config.json").exists():
        cfg = json.loads((Path(run_dir) / "config.json").read_text())
    before = int((cfg.get("init_weights") or {}).get("from_step") or 0)
    obj = {"format": 1, "kind": ckpt["kind"], "size": ckpt["size"], "step": int(ckpt["step"]) + before,
           "run_step": int(ckpt["step"]), "model": sd}
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_torch_save(obj, out)
    return {"kind": obj["kind"], "size": obj["size"], "step": obj["step"], "bytes": out.stat().st_size}


def load_packed_weights(path: str | os.PathLike, kind: str, size: str) -> dict[str, Any]:
    """Read a :func:`pack_weights` file, checking kind and size; weights back to float32.

    A file packed under a network's old kind (e.g. ``treenet``) counts as today's (``tree``).
    """
    from monodbh.models.runtime.common import canonical_kind

    w = torch.load(path, map_location="cpu", weights_only=True)
    if canonical_kind(w.get("kind")) != kind or w.get("size") != size:
        raise ValueError(f"{path}: weights are {w.get('kind')}/{w.get('size')}, the run is {kind}/{size}")
    w["model"] = {k: (v.float() if v.is_floating_point() else v) for k, v in w["model"].items()}
    return w


def _init_feeds(config: dict[str, Any], spec: Any, n: int = 4,
                seed_offset: int = 7) -> list[dict[str, np.ndarray]] | None:
    """A few inputs from the run's own training data for the warm-start check.

    Statically quantised files saturate on random inputs (the shipped tree U-Net differs from
    its own fp32 export by 24 % relative L2 on standard-normal crops), so the recovered weights
    are compared with the file on inputs like those it was calibrated on: those of the run's
    first data folder (later folders may hold another look, e.g. ``--look randomized``, on which
    an int8 file saturates more). ``None`` (random inputs) when the data source cannot be
    rebuilt from its config (e.g. in-memory lists).
    """
    try:
        data = dict(config.get("data") or {})
        if data.get("type") == "folders":
            data["folders"] = data["folders"][:1]
        src = source_from_config(data)
        return calibration_inputs(config["kind"], n, int(config.get("seed", 0)) + seed_offset, spec, src)
    except Exception:  # noqa: BLE001 - any failure: the check falls back to random inputs
        return None


def _onnx_steps(path: str | os.PathLike) -> int | None:
    """Training steps behind an ONNX file: the manifest entry next to it that names it."""
    try:
        man = json.loads((Path(path).resolve().parent / "manifest.json").read_text())
        for entry in man.get("models", {}).values():
            if entry.get("file") == Path(path).name:
                t = entry.get("training", {})
                return int(t.get("steps", 0)) + int((t.get("init_weights") or {}).get("from_step") or 0)
    except (OSError, ValueError):
        pass
    return None


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().tolist()
    if isinstance(x, Path):
        return str(x)
    return x


def load_run_model(run_dir: str | os.PathLike, map_location: str = "cpu"):
    """Build the run's model (registry kind/size from config.json) and load checkpoint weights.

    A run made under a network's old kind (e.g. ``basenet``) is built as today's (``stem_base``).

    Returns
    -------
    (model, config, checkpoint)
        ``model`` in eval mode with ``.spec``; ``checkpoint`` is the raw dict (``step`` etc.).
    """
    from monodbh.models.modeling.registry import build

    run = RunDir(run_dir)
    if not run.config_path.exists():
        raise FileNotFoundError(f"{run.config_path}: no config.json (not a training run folder)")
    config = run.read_config()
    ckpt = run.load_checkpoint(map_location)
    if ckpt is None:
        raise FileNotFoundError(f"{run.checkpoint_path}: no checkpoint")
    from monodbh.models.runtime.common import canonical_kind

    model = build(canonical_kind(config["kind"]), config["size"])
    model.load_state_dict(ckpt["model"])
    model.eval()
    return model, config, ckpt


def train_loop(run_dir: str | os.PathLike, *, config: dict[str, Any], model: torch.nn.Module,
               optimizer: torch.optim.Optimizer, steps: int,
               step_fn: Callable[[int], dict[str, float]],
               validate_fn: Callable[[], dict[str, float]] | None = None,
               resume: bool = False, scheduler: Any = None, init_weights: str | None = None,
               extra: dict[str, Any] | None = None, log_every: int = 10, val_every: int = 500,
               ckpt_every: int = 100, stop_at: int | None = None,
               verbose: bool = True) -> dict[str, Any]:
    """Generic resumable training loop.

    Parameters
    ----------
    run_dir : path
        Run folder (created).
    config : dict
        Written to config.json; must contain ``kind``, ``size``, ``seed``. ``steps`` is set here.
    model, optimizer, scheduler
        Main model (saved as ``checkpoint["model"]``, the one exported), its optimiser and an
        optional LR scheduler (anything with ``state_dict``/``load_state_dict``).
    extra : dict name -> object with state_dict/load_state_dict, optional
        Further modules/optimisers (e.g. a GAN discriminator and its optimiser), saved under
        ``checkpoint["extra"][name]``.
    step_fn : callable(step) -> dict
        Runs training step ``step`` (0-based) and returns scalar losses to log.
    validate_fn : callable() -> dict, optional
        Validation metrics; run every ``val_every`` steps and at the end.
    resume : bool
        Continue from ``checkpoint.pt`` (weights, optimiser, scheduler, RNG, step); config must
        match except ``steps`` (which may be raised; LR schedules that depend on ``steps`` then
        change from the resume point on). Log lines after the checkpoint are dropped.
    stop_at : int, optional
        Stop (with a checkpoint) after this many total steps although ``steps`` is the planned
        total: a time slice on shared machines; ``resume=True`` later continues exactly as an
        uninterrupted run to ``steps``.

    Returns
    -------
    dict
        ``{"step": final step, "val": last validation metrics or {}}``.
    """
    run = RunDir(run_dir).mkdir()
    extra = extra or {}
    start = 0
    config = dict(config, steps=int(steps))
    if resume and run.checkpoint_path.exists():
        old = run.read_config()
        for key in ("kind", "size", "seed"):
            if old.get(key) != config.get(key):
                raise ValueError(f"{run.config_path}: cannot resume, {key} differs "
                                 f"({old.get(key)!r} in run, {config.get(key)!r} requested)")
        ckpt = run.load_checkpoint(next(model.parameters()).device)
        model.load_state_dict(ckpt["model"])
        if (old.get("init_weights") or {}).get("frozen_bn"):
            from monodbh.models.training.onnx_init import freeze_bn

            freeze_bn(model)
        config = dict(config, init_weights=old.get("init_weights")) if old.get("init_weights") else config
        optimizer.load_state_dict(ckpt["optim"])
        if scheduler is not None and ckpt.get("scheduler") is not None:
            scheduler.load_state_dict(ckpt["scheduler"])
        for name, obj in extra.items():
            obj.load_state_dict(ckpt["extra"][name])
        set_rng_state(ckpt["rng"])
        start = int(ckpt["step"])
        run.truncate_log(start)
        run.write_config(config)
    else:
        if run.log_path.exists():
            run.log_path.unlink()
        seed_everything(int(config["seed"]))
        if init_weights and str(init_weights).endswith(".onnx"):
            # warm start from a shipped ONNX model (see training.onnx_init): its folded
            # BatchNorms come back as identity + bias and stay frozen (eval) from now on
            from monodbh.models.training.onnx_init import freeze_bn, load_onnx_into

            info = load_onnx_into(model, init_weights, feeds=_init_feeds(config, model.spec, n=8),
                                  calib_feeds=_init_feeds(config, model.spec, n=32, seed_offset=101))
            n_bn = freeze_bn(model) if info["folded_bn"] else 0
            config = dict(config, init_weights={
                "file": str(init_weights), "from_step": _onnx_steps(init_weights),
                "rel_l2": info["rel_l2"], "unrecovered": info["missing"], "frozen_bn": n_bn > 0})
            if verbose:
                print(f"init from {init_weights}: {info['matched']}/{info['n_float_keys']} tensors, "
                      f"outputs reproduced to {info['rel_l2']:.2%} rel. L2, {n_bn} BatchNorms frozen",
                      flush=True)
        elif init_weights:
            # warm start from a packed weights file (see pack_weights): weights only, fresh
            # optimiser and schedule
            w = load_packed_weights(init_weights, config["kind"], config["size"])
            model.load_state_dict(w["model"])
            config = dict(config, init_weights={"file": str(init_weights), "from_step": w["step"]})
        run.write_config(config)

    def save(step: int) -> None:
        run.save_checkpoint({
            "format": 1, "kind": config["kind"], "size": config["size"], "step": step,
            "model": model.state_dict(), "optim": optimizer.state_dict(),
            "scheduler": scheduler.state_dict() if scheduler is not None else None,
            "extra": {n: o.state_dict() for n, o in extra.items()},
            "rng": rng_state(), "config": config,
        })

    last_val: dict[str, float] = {}
    end = steps if stop_at is None else max(start, min(steps, int(stop_at)))
    for step in range(start, end):
        model.train()
        losses = step_fn(step)
        done = step + 1
        if done % log_every == 0 or done == steps or step == start:
            rec = {"step": done, "kind": "train", **{k: float(v) for k, v in losses.items()}}
            if scheduler is not None and hasattr(scheduler, "get_last_lr"):
                rec["lr"] = float(scheduler.get_last_lr()[0])
            run.log(rec)
            if verbose:
                print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                               for k, v in rec.items()), flush=True)
        if validate_fn is not None and (done % val_every == 0 or done == steps):
            model.eval()
            with torch.no_grad():
                last_val = {k: float(v) for k, v in validate_fn().items()}
            run.log({"step": done, "kind": "val", **last_val})
            if verbose:
                print("val", json.dumps(last_val), flush=True)
        if done % ckpt_every == 0 or done == steps or done == end:
            save(done)
    if start >= end:  # nothing to do (already finished)
        last_val = next((r for r in reversed(run.read_log()) if r.get("kind") == "val"), {})
        last_val = {k: v for k, v in last_val.items() if k not in ("step", "kind")}
    return {"step": max(start, end), "val": last_val}


# --------------------------------------------------------------------------- deterministic data order


def warmup_cosine(optimizer: torch.optim.Optimizer, warmup_steps: int,
                  steps: int) -> torch.optim.lr_scheduler.LambdaLR:
    """Linear warm-up over ``warmup_steps``, then a cosine decay to 0 at ``steps``."""
    import math

    def lr_lambda(step: int) -> float:
        if step < warmup_steps:
            return (step + 1) / warmup_steps
        return 0.5 * (1 + math.cos(math.pi * min(1.0, (step - warmup_steps) / max(1, steps - warmup_steps))))

    return torch.optim.lr_scheduler.LambdaLR(optimizer, lr_lambda)


def binary_auc(z: np.ndarray, y: np.ndarray) -> float:
    """ROC AUC of scores ``z`` (N,) for labels ``y`` (N,) (> 0 positive); NaN without both classes.

    Examples
    --------
    >>> binary_auc(np.array([0.1, 0.9, 0.4]), np.array([0, 1, 0]))
    1.0
    """
    pos, neg = z[y > 0], z[y == 0]
    if not len(pos) or not len(neg):
        return float("nan")
    order = np.argsort(np.concatenate([pos, neg]), kind="stable")
    ranks = np.empty(len(order))
    ranks[order] = np.arange(1, len(order) + 1)
    return float((ranks[:len(pos)].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg)))


def batch_indices(step: int, batch_size: int, n: int | None, seed: int) -> list[int]:
    """Sample indices of training step ``step``: pure function of its arguments.

    For a finite source (``n`` samples) a fresh permutation per epoch (seeded by
    ``(seed, epoch)``); for an infinite one (``n=None``) consecutive indices.
    """
    first = step * batch_size
    if n is None:
        return list(range(first, first + batch_size))
    out = []
    cache: dict[int, np.ndarray] = {}
    for j in range(first, first + batch_size):
        epoch, pos = divmod(j, n)
        if epoch not in cache:
            cache[epoch] = np.random.default_rng([seed, epoch, 7]).permutation(n)
        out.append(int(cache[epoch][pos]))
    return out


def sample_rng(seed: int, step: int, slot: int) -> np.random.Generator:
    """numpy Generator for augmenting item ``slot`` of step ``step`` (pure function)."""
    return np.random.default_rng([seed, step, slot, 11])


# --------------------------------------------------------------------------- data sources


class DataSource:
    """Random-access source of sample dicts. ``len()`` is ``None`` for infinite sources."""

    def __len__(self) -> int:  # pragma: no cover - overridden
        raise TypeError("infinite source")

    @property
    def n(self) -> int | None:
        """Number of samples, or ``None`` when infinite."""
        return None

    def get(self, index: int) -> dict[str, Any]:  # pragma: no cover - overridden
        raise NotImplementedError

    def config(self) -> dict[str, Any]:
        """JSON description for config.json (see :func:`source_from_config`)."""
        raise NotImplementedError

    def take(self, indices: Iterable[int]) -> list[dict[str, Any]]:
        return [self.get(i) for i in indices]


def refuse_heldout(where: Any, metas: Sequence[dict[str, Any]]) -> None:
    """Raise ``ValueError`` when one of the samples' ``metas`` is of the held-out look
    (``dbh synth --look heldout``): it is for evaluation only, never for training, validation
    during training or quantization (``where`` names the data in the message)."""
    from monodbh.models.synthetic.looks import HELDOUT
    if any((m or {}).get("look") == HELDOUT for m in metas):
        raise ValueError(f"{where}: samples of the held-out look (dbh synth --look heldout) are for "
                         "evaluation only and are never trained, validated or calibrated on")


class ListSource(DataSource):
    """In-memory list of sample dicts (tests; not serialisable to config beyond its length)."""

    def __init__(self, samples: Sequence[dict[str, Any]]) -> None:
        self.samples = list(samples)

    def __len__(self) -> int:
        return len(self.samples)

    @property
    def n(self) -> int:
        return len(self.samples)

    def get(self, index: int) -> dict[str, Any]:
        return self.samples[index % len(self.samples)]

    def config(self) -> dict[str, Any]:
        return {"type": "list", "n": len(self.samples)}


class FolderSource(DataSource):
    """Samples of one or more ``dbh synth`` folders (concatenated, in listed order).

    Uses ``monodbh.models.synthetic.io.list_samples(folder)`` and ``read_sample(folder, index)``.
    ``cache`` keeps up to that many decoded samples in memory (LRU). ``segmasks``: also read
    the segmenter's mask ``NNNNNN.segmask.png`` (key ``segmask``) where it exists.
    """

    def __init__(self, folders: str | os.PathLike | Sequence[str | os.PathLike],
                 cache: int = 0, segmasks: bool = False, allow_heldout: bool = False) -> None:
        from monodbh.models.synthetic import io as sio

        self.segmasks = segmasks     # also read NNNNNN.segmask.png (training.segmasks) as "segmask"
        self._io = sio
        if isinstance(folders, (str, os.PathLike)):
            folders = [folders]
        self.folders = [Path(f) for f in folders]
        self.items: list[tuple[Path, Any]] = []
        for f in self.folders:
            if not f.is_dir():
                raise FileNotFoundError(f"{f}: data folder not found")
            idx = sio.list_samples(f)
            if idx and not allow_heldout:
                refuse_heldout(f, [sio.read_sample(f, i, arrays=False)["meta"] for i in {idx[0], idx[-1]}])
            self.items += [(f, i) for i in idx]
        if not self.items:
            raise FileNotFoundError(f"{', '.join(map(str, self.folders))}: no samples found")
        self._cache: OrderedDict[int, dict[str, Any]] = OrderedDict()
        self._cache_size = cache

    def __len__(self) -> int:
        return len(self.items)

    @property
    def n(self) -> int:
        return len(self.items)

    def get(self, index: int) -> dict[str, Any]:
        index %= len(self.items)
        if index in self._cache:
            self._cache.move_to_end(index)
            return self._cache[index]
        folder, i = self.items[index]
        s = self._io.read_sample(folder, i)
        if self.segmasks:
            from .segmasks import read_segmask
            m = read_segmask(folder, i)
            if m is not None:
                s["segmask"] = m
        if self._cache_size:
            self._cache[index] = s
            if len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return s

    def config(self) -> dict[str, Any]:
        out = {"type": "folders", "folders": [str(f.resolve()) for f in self.folders]}
        if self.segmasks:
            out["segmasks"] = True
        return out


class GeneratorSource(DataSource):
    """Samples rendered on the fly by the synthetic generator.

    Sample ``index`` is ``monodbh.models.synthetic.generate_sample(seed, index, size, **opts)``,
    i.e. exactly sample ``index`` of ``dbh synth`` with the same seed and size (random access,
    deterministic). ``pool``: if given, indices wrap modulo ``pool`` (a finite pseudo-dataset, so
    the LRU ``cache`` of rendered samples is reused across epochs; default cache = pool).
    Rendering costs about 1-2 s per sample on one core: prefer a ``dbh synth`` folder.
    """

    def __init__(self, seed: int = 0, size: tuple[int, int] = (320, 240),
                 opts: dict[str, Any] | None = None, pool: int | None = None,
                 cache: int = 0) -> None:
        self.seed = int(seed)
        self.size = (int(size[0]), int(size[1]))
        self.opts = dict(opts or {})
        refuse_heldout(f"generator seed {self.seed}", [self.opts])
        self.pool = pool
        self._cache: OrderedDict[int, dict[str, Any]] = OrderedDict()
        self._cache_size = cache if cache else (pool or 0)

    def __len__(self) -> int:
        if self.pool is None:
            raise TypeError("infinite generator source has no len(); use .n")
        return self.pool

    @property
    def n(self) -> int | None:
        return self.pool

    def get(self, index: int) -> dict[str, Any]:
        if self.pool is not None:
            index %= self.pool
        if index in self._cache:
            self._cache.move_to_end(index)
            return self._cache[index]
        from monodbh.models.synthetic import generate_sample

        s = generate_sample(self.seed, index, self.size, **self.opts)
        s.pop("scene", None)  # renderer objects: not needed for training, large
        if self._cache_size:
            self._cache[index] = s
            if len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return s

    def config(self) -> dict[str, Any]:
        return {"type": "generator", "seed": self.seed, "size": list(self.size),
                "opts": self.opts, "pool": self.pool}


def config_from_dict(cls: type, d: dict[str, Any], what: str) -> Any:
    """``cls(**d)`` for a training-config dataclass, refusing unknown keys (ValueError naming
    ``what``, e.g. ``"stem_base"``)."""
    unknown = set(d) - {f.name for f in fields(cls)}
    if unknown:
        raise ValueError(f"unknown {what} training options {sorted(unknown)}")
    return cls(**d)


class BankSource(DataSource):
    """Examples already cut into ``.npz`` banks (the rope verifier's, see
    ``monodbh.toolkit.evaluation.fit_rope_stem.collect_patches``), concatenated in listed order.

    ``arrays`` holds every array of the banks (first axis: the example); ``n`` counts examples.
    """

    def __init__(self, paths: str | os.PathLike | Sequence[str | os.PathLike]) -> None:
        if isinstance(paths, (str, os.PathLike)):
            paths = [paths]
        self.paths = [Path(p) for p in paths]
        parts = []
        for p in self.paths:
            if not p.is_file():
                raise FileNotFoundError(f"{p}: example bank not found")
            with np.load(p) as z:
                parts.append({k: z[k] for k in z.files})
        keys = set(parts[0])
        for k, p in enumerate(parts):
            if set(p) != keys:
                raise ValueError(f"{self.paths[k]}: bank arrays {sorted(p)} differ from {sorted(keys)}")
            p["bank"] = np.full(len(p["label"]) if "label" in p else len(next(iter(p.values()))), k, np.int64)
        self.arrays = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
        self._n = len(self.arrays["bank"])

    def __len__(self) -> int:
        return self._n

    @property
    def n(self) -> int:
        return self._n

    def get(self, index: int) -> dict[str, Any]:
        return {k: v[index % self._n] for k, v in self.arrays.items()}

    def config(self) -> dict[str, Any]:
        return {"type": "banks", "paths": [str(p.resolve()) for p in self.paths]}


def bank_source(data: Any, missing: str, wrong: str, key: str | None = None) -> BankSource:
    """The :class:`BankSource` of ``data`` (``.npz`` paths) for a bank-trained kind.

    Raises ``ValueError(missing)`` when ``data`` is None, and ``ValueError(wrong + ", got ...")``
    when it is no bank (or a bank without the array ``key``).
    """
    if data is None:
        raise ValueError(missing)
    src = make_source(data)
    if not isinstance(src, BankSource) or (key is not None and key not in src.arrays):
        raise ValueError(f"{wrong}, got {src.config()}")
    return src


def bank_run_sources(run_dir: str | os.PathLike, resume: bool, options: dict[str, Any], data: Any,
                     val_data: Any, source_fn: Callable[[Any], BankSource]
                     ) -> tuple[dict[str, Any], BankSource, BankSource | None]:
    """Options and banks of a bank-trained run: ``(options, train source, validation source or None)``.

    On ``resume`` the run's own config.json fills in what the call leaves out (its options
    under the call's, its ``data`` and ``val_data`` where the call gives none). ``source_fn``
    turns a data value into a :class:`BankSource` (e.g. a kind's :func:`bank_source` wrapper).
    """
    run = RunDir(run_dir)
    if resume and run.config_path.exists():
        old = run.read_config()
        options = {**old.get("train", {}), **options}
        data = data if data is not None else old.get("data")
        val_data = val_data if val_data is not None else old.get("val_data")
    return options, source_fn(data), (source_fn(val_data) if val_data is not None else None)


def resumed_folder_run(run_dir: str | os.PathLike, resume: bool, options: dict[str, Any], data: Any,
                       val_data: Any) -> tuple[dict[str, Any], Any, Any, int | None]:
    """``(options, data, val_data, train_indices)`` of a run that cuts its examples from
    ``dbh synth`` folders (the stem-base and stem-edge networks).

    On ``resume`` the run's own config.json fills in what the call leaves out (its options under
    the call's, its ``data`` and validation folders where the call gives none) and gives the
    number of training samples its bank was cut from (None for a new run), so that the same bank
    is cut again.
    """
    run = RunDir(run_dir)
    if not (resume and run.config_path.exists()):
        return options, data, val_data, None
    old = run.read_config()
    options = {**old.get("train", {}), **options}
    data = data if data is not None else old.get("data")
    val_data = val_data if val_data is not None else (old.get("val_data") or {}).get("folders")
    return options, data, val_data, old.get("train_indices")


def held_out_split(src: DataSource, vsrc: DataSource | None, val_n: int, train_indices: int | None
                   ) -> tuple[DataSource, list[int], list[int]]:
    """``(validation source, training indices, validation indices)``: the first ``val_n`` samples
    of ``vsrc`` and all of ``src``; without ``vsrc``, the last ``val_n`` samples of ``src``, left
    out of training. ``train_indices`` (a resumed run's) keeps the training bank's first samples."""
    n = src.n
    if vsrc is not None:
        val_idx = list(range(min(val_n, vsrc.n)))
        train_idx = list(range(n))
    else:
        vsrc = src
        val_idx = list(range(max(0, n - val_n), n))
        train_idx = list(range(0, max(0, n - val_n)))
    if train_indices is not None:
        train_idx = list(range(int(train_indices)))    # the same bank on resume
    return vsrc, train_idx, val_idx


def held_out_bank(cache: dict[str, Any], kind: str, data: DataSource | None, n: int, val_n: int,
                  build: Callable[[DataSource, list[int]], dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Up to ``n`` examples of the bank ``build(data, indices)`` cuts from the last ``val_n``
    samples of ``data`` (the held-out end of the folder), kept in ``cache`` while ``data`` is the
    same source of the same length (``dbh export`` scores every int8 recipe on the same bank)."""
    if data is None:
        raise ValueError(f"{kind} export needs data (the run's config.json names its folders)")
    if cache.get("data") is not data or cache.get("n") != data.n:
        idx = list(range(max(0, data.n - val_n), data.n))
        cache.update(data=data, n=data.n, bank=build(data, idx))
    return {k: v[:n] for k, v in cache["bank"].items()}


def source_from_config(cfg: dict[str, Any]) -> DataSource:
    """Inverse of :meth:`DataSource.config` (``"list"`` sources cannot be rebuilt)."""
    t = cfg.get("type")
    if t == "banks":
        return BankSource(cfg["paths"])
    if t == "folders":
        return FolderSource(cfg["folders"], cache=cfg.get("cache", 0), segmasks=bool(cfg.get("segmasks", False)))
    if t == "generator":
        return GeneratorSource(cfg.get("seed", 0), tuple(cfg.get("size", (320, 240))),
                               cfg.get("opts"), cfg.get("pool"), cfg.get("cache", 0))
    raise ValueError(f"cannot rebuild data source from {cfg!r}")


def make_source(data: Any, *, default_seed: int = 0,
                size: tuple[int, int] = (320, 240), allow_heldout: bool = False) -> DataSource:
    """Build a :class:`DataSource` from a flexible value.

    Accepted: a ``DataSource``; a list of sample dicts; a folder path or list of folder paths;
    a config dict (:func:`source_from_config`); ``.npz`` example bank path(s) (:class:`BankSource`); the string ``"gen"`` / ``"gen:SEED"`` /
    ``"gen:SEED:POOL"`` (generator at ``size``). Folders of the held-out look are refused
    (:func:`refuse_heldout`) unless ``allow_heldout`` (evaluation).
    """
    if isinstance(data, DataSource):
        return data
    if isinstance(data, dict):
        return source_from_config(data)
    if isinstance(data, str) and (data == "gen" or data.startswith("gen:")):
        parts = data.split(":")
        seed = int(parts[1]) if len(parts) > 1 and parts[1] else default_seed
        pool = int(parts[2]) if len(parts) > 2 and parts[2] else None
        return GeneratorSource(seed, size, pool=pool)
    if isinstance(data, (list, tuple)) and data and isinstance(data[0], dict):
        if not allow_heldout:
            refuse_heldout("samples", [d.get("meta") for d in data])
        return ListSource(data)
    items = [data] if isinstance(data, (str, os.PathLike)) else data
    if isinstance(items, (list, tuple)) and items and all(str(x).endswith(".npz") for x in items):
        return BankSource(list(items))
    if isinstance(data, (str, os.PathLike, list, tuple)):
        return FolderSource(data, allow_heldout=allow_heldout)
    raise TypeError(f"cannot make a data source from {type(data).__name__}")


# --------------------------------------------------------------------------- augmentation

#: Keys of (H, W[, C]) arrays moved by geometric augmentation. Others are left alone.
#: (``segmask``: the shipped segmenter's tree mask, where ``training.segmasks`` wrote one)
SPATIAL_KEYS: tuple[str, ...] = ("rgb", "depth", "semantic", "instance", "rope", "z1", "z2", "segmask")


@dataclass
class AugmentConfig:
    """Augmentation parameters (paper sec. 2.1/3.1: colour, brightness, contrast, blur, flip, crop).

    Probabilities are per sample; ranges are symmetric jitter amplitudes.
    """

    hflip: float = 0.5
    crop: float = 0.5              #: probability of a random crop (then resized to out_size)
    crop_min_area: float = 0.4     #: min crop area as a fraction of the image
    crop_aspect: tuple[float, float] = (0.75, 1.333)  #: crop w/h relative to the image's w/h
    brightness: float = 0.25
    contrast: float = 0.25
    saturation: float = 0.25
    hue_deg: float = 6.0
    blur: float = 0.2              #: probability of a Gaussian blur
    blur_sigma: tuple[float, float] = (0.3, 1.5)
    noise_std: float = 0.0         #: additive Gaussian noise on 0..255 scale (0 = off)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


#: named augmentation settings (``dbh train segmenter --augment NAME``); "strong" is the
#: session-5 segmenter run's: wider colour jitter against the synthetic look
AUGMENT_PRESETS = {
    "default": AugmentConfig(),
    "strong": AugmentConfig(brightness=0.35, contrast=0.35, saturation=0.45, hue_deg=15.0, blur=0.3,
                            noise_std=3.0),
}


def photometric(rgb: np.ndarray, rng: np.random.Generator, cfg: AugmentConfig) -> np.ndarray:
    """Colour jitter, brightness, contrast, saturation, hue, blur, noise on ``rgb`` (H, W, 3) uint8.

    Returns a new uint8 array of the same shape.
    """
    x = rgb.astype(np.float32) / 255.0
    ops = rng.permutation(4)
    for op in ops:
        if op == 0 and cfg.brightness:
            x = x * rng.uniform(1 - cfg.brightness, 1 + cfg.brightness)
        elif op == 1 and cfg.contrast:
            m = x.mean()
            x = (x - m) * rng.uniform(1 - cfg.contrast, 1 + cfg.contrast) + m
        elif op == 2 and cfg.saturation:
            g = x @ np.array([0.299, 0.587, 0.114], np.float32)
            x = (x - g[..., None]) * rng.uniform(1 - cfg.saturation, 1 + cfg.saturation) + g[..., None]
        elif op == 3 and cfg.hue_deg:
            dh = rng.uniform(-cfg.hue_deg, cfg.hue_deg)
            hsv = cv2.cvtColor(np.clip(x, 0, 1), cv2.COLOR_RGB2HSV)
            hsv[..., 0] = (hsv[..., 0] + dh) % 360.0
            x = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
    if cfg.blur and rng.random() < cfg.blur:
        s = rng.uniform(*cfg.blur_sigma)
        x = cv2.GaussianBlur(x, (0, 0), sigmaX=s, sigmaY=s)
    x = np.clip(x * 255.0, 0, 255)
    if cfg.noise_std:
        x = np.clip(x + rng.normal(0, cfg.noise_std, x.shape), 0, 255)
    return (x + 0.5).astype(np.uint8)


def _warp_K(K: np.ndarray | None, x0: float, y0: float, sx: float, sy: float,
            flip_w: int | None) -> np.ndarray | None:
    if K is None:
        return None
    K = np.array(K, dtype=np.float64).copy()
    K[0, 0] *= sx
    K[1, 1] *= sy
    K[0, 2] = (K[0, 2] - x0 + 0.5) * sx - 0.5
    K[1, 2] = (K[1, 2] - y0 + 0.5) * sy - 0.5
    if flip_w is not None:
        K[0, 2] = flip_w - 1 - K[0, 2]
    return K


def _resize_array(key: str, a: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    w, h = size
    if a.shape[1] == w and a.shape[0] == h:
        return a
    if key == "rgb":
        interp = cv2.INTER_AREA if a.shape[1] > w else cv2.INTER_LINEAR
        return cv2.resize(a, (w, h), interpolation=interp)
    # labels and depths: nearest (never mix depths across object edges)
    if a.dtype == bool:
        return cv2.resize(a.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
    if a.dtype == np.uint16 or a.dtype == np.uint8 or a.dtype == np.float32:
        return cv2.resize(a, (w, h), interpolation=cv2.INTER_NEAREST)
    return cv2.resize(a.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST).astype(a.dtype)


def _meta_K(sample: dict[str, Any]) -> np.ndarray | None:
    if "K" in sample:
        return np.asarray(sample["K"], dtype=np.float64)
    meta = sample.get("meta") or {}
    return np.asarray(meta["K"], dtype=np.float64) if "K" in meta else None


def geometric(sample: dict[str, Any], rng: np.random.Generator, cfg: AugmentConfig,
              out_size: tuple[int, int], fit: int | None = None) -> dict[str, Any]:
    """Random crop (then resize to ``out_size`` = (W, H)) and horizontal flip of all spatial arrays.

    With ``fit`` (pixels), ``out_size`` is ignored and the crop keeps its aspect ratio, resized
    so that its longer side is ``fit`` (a portrait crop of a landscape scene stays portrait).

    ``rgb`` is resized with area/linear interpolation, label and depth arrays with nearest.
    Returns a shallow copy of ``sample`` with new arrays, ``K`` (3, 3) float64 adjusted for the
    crop/resize/flip (when the sample has ``meta['K']``) and ``aug`` =
    ``{"crop": [x0, y0, w, h], "flip": bool}`` in source pixels.
    Depth values are unchanged (a crop-resize changes the focal length, recorded in ``K``).
    """
    H, W = sample["rgb"].shape[:2]
    x0, y0, cw, ch = 0, 0, W, H
    if cfg.crop and rng.random() < cfg.crop:
        for _ in range(10):
            area = rng.uniform(cfg.crop_min_area, 1.0) * W * H
            ar = np.exp(rng.uniform(np.log(cfg.crop_aspect[0]), np.log(cfg.crop_aspect[1]))) * W / H
            w = int(round(np.sqrt(area * ar)))
            h = int(round(np.sqrt(area / ar)))
            if 8 <= w <= W and 8 <= h <= H:
                x0 = int(rng.integers(0, W - w + 1))
                y0 = int(rng.integers(0, H - h + 1))
                cw, ch = w, h
                break
    flip = bool(cfg.hflip and rng.random() < cfg.hflip)
    if fit is not None:
        sc = fit / max(cw, ch)
        out_size = (min(fit, max(1, int(round(cw * sc)))), min(fit, max(1, int(round(ch * sc)))))
    out = dict(sample)
    for key in SPATIAL_KEYS:
        if key not in sample or sample[key] is None:
            continue
        a = np.ascontiguousarray(sample[key][y0:y0 + ch, x0:x0 + cw])
        a = _resize_array(key, a, out_size)
        if flip:
            a = np.ascontiguousarray(a[:, ::-1])
        out[key] = a
    K = _meta_K(sample)
    out["K"] = _warp_K(K, x0, y0, out_size[0] / cw, out_size[1] / ch, out_size[0] if flip else None)
    out["aug"] = {"crop": [x0, y0, cw, ch], "flip": flip}
    return out


def resize_sample(sample: dict[str, Any], out_size: tuple[int, int]) -> dict[str, Any]:
    """Resize all spatial arrays to ``out_size`` = (W, H) (no augmentation; validation/export)."""
    H, W = sample["rgb"].shape[:2]
    out = dict(sample)
    for key in SPATIAL_KEYS:
        if key in sample and sample[key] is not None:
            out[key] = _resize_array(key, sample[key], out_size)
    out["K"] = _warp_K(_meta_K(sample), 0, 0, out_size[0] / W, out_size[1] / H, None)
    out["aug"] = {"crop": [0, 0, W, H], "flip": False}
    return out


def augment(sample: dict[str, Any], rng: np.random.Generator, cfg: AugmentConfig | None,
            out_size: tuple[int, int], fit: int | None = None) -> dict[str, Any]:
    """:func:`geometric` then :func:`photometric` on ``rgb``; ``cfg=None`` = just resize."""
    if cfg is None:
        return resize_sample(sample, out_size)
    out = geometric(sample, rng, cfg, out_size, fit=fit)
    out["rgb"] = photometric(out["rgb"], rng, cfg)
    return out


# --------------------------------------------------------------------------- export hooks

#: kind -> training module that registers its hooks (imported lazily).
TRAINING_MODULES: dict[str, str] = {
    "segmenter": "monodbh.models.training.segmenter",
    "depth": "monodbh.models.training.depth",
    "tree": "monodbh.models.training.tree",
    "stem_base": "monodbh.models.training.stem_base",
    "stem_edge": "monodbh.models.training.stem_edge",
    "rope_verifier": "monodbh.models.training.rope_verifier",
    "rope_finder": "monodbh.models.training.rope_finder",
}
_CALIB_HOOKS: dict[str, Callable[..., list[dict[str, np.ndarray]]]] = {}
_EVAL_HOOKS: dict[str, Callable[..., dict[str, float]]] = {}


def register_calibration(kind: str) -> Callable:
    """Decorator: ``fn(n, seed, spec, data) -> list of {input name: array of spec shape}``.

    ``spec`` is the :class:`ModelSpec` to feed, ``data`` a :class:`DataSource` or ``None`` (the
    kind's default, normally the generator). Used for int8 calibration and for the fp32/int8
    comparison inputs.
    """

    def deco(fn: Callable) -> Callable:
        _CALIB_HOOKS[kind] = fn
        return fn

    return deco


def register_eval(kind: str) -> Callable:
    """Decorator: ``fn(predict, n, seed, spec, data) -> dict of metrics`` (includes ``spec.metric``).

    ``predict(feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]`` runs one model (fp32 or
    int8 onnxruntime session, or torch) on one batch-1 input; the hook builds inputs from its own
    samples (with ground truth) and scores the outputs.
    """

    def deco(fn: Callable) -> Callable:
        _EVAL_HOOKS[kind] = fn
        return fn

    return deco


def _ensure_hooks(kind: str, table: dict) -> None:
    if kind not in table and kind in TRAINING_MODULES:
        importlib.import_module(TRAINING_MODULES[kind])
    if kind not in table:
        raise KeyError(f"no hook registered for kind {kind!r}")


def calibration_inputs(kind: str, n: int, seed: int, spec: Any = None,
                       data: DataSource | None = None) -> list[dict[str, np.ndarray]]:
    """``n`` input feeds for ``kind`` from its registered calibration hook."""
    from monodbh.models.modeling.registry import get_spec

    _ensure_hooks(kind, _CALIB_HOOKS)
    return _CALIB_HOOKS[kind](n, seed, spec or get_spec(kind, "base"), data)


def evaluate_kind(kind: str, predict: Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]],
                  n: int, seed: int, spec: Any = None,
                  data: DataSource | None = None) -> dict[str, float]:
    """Task metrics of ``predict`` on ``n`` evaluation samples (registered eval hook)."""
    from monodbh.models.modeling.registry import get_spec

    _ensure_hooks(kind, _EVAL_HOOKS)
    return _EVAL_HOOKS[kind](predict, n, seed, spec or get_spec(kind, "base"), data)
