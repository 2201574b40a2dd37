"""Weight-space blending of a fine-tuned run with the model it started from (``dbh train-blend``).

Training-only; imported by :mod:`monodbh.cli.train_cmd`. A network fine-tuned on a new look
(domain randomisation) gains robustness on unseen looks and can lose some of what it knew;
the straight line between the starting weights and the fine-tuned ones often keeps the best of
both (Wortsman et al. 2022, "Robust fine-tuning of zero-shot models", WiSE-FT). This holds for
a warm start whose BatchNorm statistics were frozen (``init_weights.frozen_bn`` in the run's
config.json), so that both ends normalise alike; :func:`blend_run` refuses other runs.
"""
from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path
from typing import Any

import torch

from .common import RunDir, atomic_torch_save

__all__ = ["blend_state_dicts", "blend_run"]


def blend_state_dicts(start: dict[str, torch.Tensor], tuned: dict[str, torch.Tensor],
                      alpha: float) -> dict[str, torch.Tensor]:
    """``(1 - alpha) * start + alpha * tuned`` for every floating tensor; integer tensors (BatchNorm
    counters) are the tuned ones. Both dicts must have the same keys and shapes.

    Examples
    --------
    >>> a, b = {"w": torch.zeros(2)}, {"w": torch.ones(2)}
    >>> blend_state_dicts(a, b, 0.25)["w"].tolist()
    [0.25, 0.25]
    """
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must be in [0, 1], got {alpha}")
    if set(start) != set(tuned):
        raise ValueError(f"the weights differ in keys: {sorted(set(start) ^ set(tuned))[:5]}")
    out = {}
    for k, v in tuned.items():
        s = start[k]
        if s.shape != v.shape:
            raise ValueError(f"{k}: shape {tuple(s.shape)} against {tuple(v.shape)}")
        out[k] = ((1.0 - alpha) * s.float() + alpha * v.float()).to(v.dtype) if v.is_floating_point() else v
    return out


def blend_run(run_dir: str | os.PathLike, out_dir: str | os.PathLike, alpha: float,
              start: str | os.PathLike | None = None) -> dict[str, Any]:
    """Write ``out_dir``: a run folder whose checkpoint holds ``run_dir``'s weights blended with
    its starting weights by ``alpha`` (1: the fine-tuned run, 0: where it started), for
    ``dbh export``.

    Parameters
    ----------
    run_dir : a finished run started with ``--init`` (its config's ``init_weights``).
    out_dir : the new run folder (must not exist).
    alpha : the fine-tuned run's share, in [0, 1].
    start : the starting weights' file (default: the run's ``init_weights.file``); an ONNX file
        of the same kind and size (``models/KIND_int8.onnx``).

    Returns
    -------
    The ``blend`` record also stored in the new config.json: ``{"alpha", "start", "start_sha256",
    "tuned_run"}``.
    """
    from monodbh.models.modeling import registry
    from .onnx_init import state_dict_from_onnx

    src, dst = RunDir(run_dir), RunDir(out_dir)
    if dst.path.exists():
        raise FileExistsError(f"{dst.path}: already exists")
    config = src.read_config()
    init = config.get("init_weights") or {}
    if not init.get("frozen_bn"):
        raise ValueError(f"{src.path}: not a warm start with frozen BatchNorm; blending needs one")
    start = Path(start or init.get("file") or "")
    if not start.is_file():
        raise FileNotFoundError(f"{start}: starting weights not found")
    ckpt = src.load_checkpoint()
    if ckpt is None:
        raise FileNotFoundError(f"{src.checkpoint_path}: no checkpoint")
    model = registry.build(ckpt["kind"], ckpt["size"])
    start_sd, _ = state_dict_from_onnx(start, model)
    blend = {"alpha": float(alpha), "start": str(start),
             "start_sha256": hashlib.sha256(start.read_bytes()).hexdigest(), "tuned_run": str(src.path.resolve())}
    ckpt = dict(ckpt, model=blend_state_dicts(start_sd, ckpt["model"], alpha))
    for k in ("optim", "scheduler"):
        ckpt.pop(k, None)
    dst.mkdir()
    atomic_torch_save(ckpt, dst.checkpoint_path)
    dst.write_config(dict(config, blend=blend))
    if src.log_path.exists():
        shutil.copy(src.log_path, dst.log_path)
    return blend
