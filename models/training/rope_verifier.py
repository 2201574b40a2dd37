"""Training of the rope-band verifier: ``dbh train rope_verifier``.

Examples are cut once per ``dbh synth`` folder into an ``.npz`` bank by
``python -m monodbh.toolkit.evaluation.fit_rope_stem --bank FOLDER OUT.npz`` (the pipeline's own
segmenter and stem search run on every photo: each candidate band gives its patch
(:func:`monodbh.models.runtime.rope_verifier.band_patch`), the stem search's features and a label, on the
true rope or not). Training draws batches from the banks with a fixed share of positives
(``pos_frac``), photometric augmentation, mirror flips and a +-1 row shift. Loss: binary
cross-entropy.

Validation (:func:`rope_metrics`): ``auc`` over all bands, and the photo-level outcome the
pipeline sees: on roped photos where the band detector did not find the rope, is the best
band the rope (``top1``)?
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Any, Callable

import numpy as np
import torch
from torch.nn import functional as F

from monodbh.models.modeling.registry import build
from monodbh.models.runtime.rope_verifier import patch_feed
from monodbh.models.training.common import (AugmentConfig, BankSource, DataSource, bank_run_sources,
                                            bank_source, binary_auc, config_from_dict, photometric,
                                            register_calibration, register_eval, select_device, train_loop,
                                            warmup_cosine)

__all__ = ["RopeVerifierTrainConfig", "rope_metrics", "train_rope_verifier"]


@dataclass
class RopeVerifierTrainConfig:
    """Hyper-parameters of :func:`train_rope_verifier` (stored in config.json)."""

    size: str = "base"
    seed: int = 0
    batch_size: int = 128
    lr: float = 2e-3
    weight_decay: float = 1e-4
    warmup_steps: int = 100
    pos_frac: float = 0.25          #: share of positives per batch
    threads: int | None = None
    log_every: int = 50
    val_every: int = 500
    ckpt_every: int = 250
    augment: dict[str, Any] = field(default_factory=lambda: dict(
        hflip=0.5, brightness=0.25, contrast=0.25, saturation=0.25, hue_deg=5.0, blur=0.2,
        blur_sigma=(0.3, 0.8), noise_std=2.0))

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "RopeVerifierTrainConfig":
        return config_from_dict(cls, d, "rope_verifier")


# --------------------------------------------------------------------------- metrics


def rope_metrics(z: np.ndarray, bank: dict[str, np.ndarray]) -> dict[str, float]:
    """Band- and photo-level metrics of logits ``z`` (N,) on a bank's bands.

    ``auc``: positives vs negatives over all bands. Photo level, trunk-like bands only, on
    photos of one source (``bank`` x ``photo``): ``top1`` the share of roped photos (the band
    detector missed) whose best band is the rope; ``rope_free_max`` the median of the best
    logit on rope-free photos (a threshold must lie above these).
    """
    y = bank["label"].astype(np.int64)
    out = {"n": float(len(y)), "n_pos": float(y.sum()), "auc": binary_auc(z, y)}
    key = bank["bank"] * 1_000_000 + bank["photo"]
    tl = bank["trunk_like"].astype(bool)
    top, n_missed, best_free = 0, 0, []
    for k in np.unique(key):
        sel = (key == k) & tl
        if not sel.any():
            continue
        i = np.flatnonzero(sel)[int(np.argmax(z[sel]))]
        if bank["roped"][i]:
            if bank["found_by_band"][i]:
                continue
            n_missed += 1
            top += int(y[i] > 0)
        else:
            best_free.append(float(z[i]))
    out["top1"] = top / max(n_missed, 1)
    out["n_missed_by_band"] = float(n_missed)
    if best_free:
        out["rope_free_max"] = float(np.median(best_free))
    return out


# --------------------------------------------------------------------------- training


def _feed(bank: dict[str, np.ndarray], k: int, rng: np.random.Generator | None, aug: AugmentConfig | None):
    p = bank["patch"][k]
    st, ins = bank["stem"][k], bank["inside"][k]
    if rng is not None:
        p = photometric(p, rng, aug)
        sh = int(rng.integers(-1, 2))
        if sh:
            p, st, ins = (np.roll(a, sh, axis=0) for a in (p, st, ins))
    x = patch_feed(p, st, ins)
    if rng is not None and rng.random() < aug.hflip:
        x = x[..., ::-1]
    return x


def _bank_source(data: Any) -> BankSource:
    return bank_source(data, "dbh train rope_verifier needs --data (.npz banks of fit_rope_stem --bank)",
                       "dbh train rope_verifier: --data must be .npz example banks")


def train_rope_verifier(run_dir: str, steps: int = 3000, data: Any = None, resume: bool = False, *,
                  val_data: Any = None, stop_at: int | None = None, verbose: bool = True,
                  init_weights: str | None = None, **options: Any) -> dict[str, Any]:
    """Train the rope verifier into ``run_dir`` (``dbh train rope_verifier``).

    Parameters
    ----------
    run_dir, steps, resume, stop_at, init_weights : as the other ``dbh train`` kinds.
    data : ``.npz`` bank(s) to train on.
    val_data : bank(s) for validation (default: none, only the training loss is logged).
    **options : fields of :class:`RopeVerifierTrainConfig`.

    Returns
    -------
    dict ``{"step", "val", "bank"}``.
    """
    options, src, vsrc = bank_run_sources(run_dir, resume, options, data, val_data, _bank_source)
    cfg = RopeVerifierTrainConfig.from_dict(options)
    device = select_device(cfg.threads)
    torch.manual_seed(cfg.seed)
    bank = src.arrays
    vbank = vsrc.arrays if vsrc is not None else None
    y = bank["label"].astype(np.float32)
    pos, neg = np.flatnonzero(y > 0), np.flatnonzero(y == 0)
    if not len(pos) or not len(neg):
        raise ValueError(f"{src.config()}: the banks need bands on and off the rope")
    if verbose:
        print(f"bank: {len(y)} training bands ({len(pos)} on the rope)"
              + (f", {vsrc.n} validation bands" if vsrc is not None else ""), flush=True)
    model = build("rope_verifier", cfg.size).to(device)
    with torch.no_grad():
        model.side_mean.copy_(torch.from_numpy(bank["side"].mean(0)))
        model.side_std.copy_(torch.from_numpy(bank["side"].std(0) + 1e-3))
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)

    sched = warmup_cosine(opt, cfg.warmup_steps, steps)
    aug = AugmentConfig(**{**cfg.augment, "blur_sigma": tuple(cfg.augment.get("blur_sigma", (0.3, 0.8)))})
    timing = {"t": 0.0, "n": 0}
    n_pos = max(1, int(round(cfg.pos_frac * cfg.batch_size)))

    def step_fn(step: int) -> dict[str, float]:
        t0 = time.perf_counter()
        rng = np.random.default_rng([cfg.seed, step, 29])
        idx = np.concatenate([rng.choice(pos, n_pos), rng.choice(neg, cfg.batch_size - n_pos)])
        x = torch.from_numpy(np.ascontiguousarray(np.stack([_feed(bank, k, rng, aug) for k in idx]))).to(device)
        s = torch.from_numpy(bank["side"][idx]).to(device)
        t = torch.from_numpy(y[idx]).to(device)
        z = model(x, s)[:, 0]
        loss = F.binary_cross_entropy_with_logits(z, t)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
        opt.step()
        sched.step()
        timing["t"] += time.perf_counter() - t0
        timing["n"] += len(idx)
        return {"loss": float(loss.detach()), "bands_per_s": timing["n"] / max(timing["t"], 1e-9)}

    def predict_bank(b: dict[str, np.ndarray]) -> np.ndarray:
        zs = []
        for k0 in range(0, len(b["label"]), 512):
            ks = range(k0, min(k0 + 512, len(b["label"])))
            x = torch.from_numpy(np.stack([_feed(b, k, None, None) for k in ks])).to(device)
            s = torch.from_numpy(b["side"][k0:k0 + 512]).to(device)
            zs.append(0.5 * (model(x, s) + model(x.flip(3), s))[:, 0].cpu().numpy())
        return np.concatenate(zs)

    def validate_fn() -> dict[str, float]:
        if vbank is None:
            return {}
        return rope_metrics(predict_bank(vbank), vbank)

    config = {"kind": "rope_verifier", "size": cfg.size, "seed": cfg.seed, "batch_size": cfg.batch_size,
              "train": asdict(cfg), "data": src.config(), "val_data": vsrc.config() if vsrc is not None else None,
              "bank_bands": int(len(y))}
    res = train_loop(run_dir, init_weights=init_weights, config=config, model=model, optimizer=opt, steps=steps,
                     step_fn=step_fn, validate_fn=validate_fn, resume=resume, scheduler=sched,
                     log_every=cfg.log_every, val_every=cfg.val_every, ckpt_every=cfg.ckpt_every,
                     verbose=verbose, **({"stop_at": stop_at} if stop_at is not None else {}))
    res["bank"] = int(len(y))
    return res


# --------------------------------------------------------------------------- export hooks


def _eval_bands(n: int, seed: int, data: DataSource | None) -> list[int]:
    """Up to ``n`` band indices of ``data``: a third on the rope, the rest drawn at random."""
    if not isinstance(data, BankSource):
        raise ValueError("rope_verifier export needs its .npz banks (the run's config.json names them)")
    y = data.arrays["label"]
    rng = np.random.default_rng(seed)
    pos, neg = np.flatnonzero(y > 0), np.flatnonzero(y == 0)
    k = min(len(pos), n // 3)
    return sorted(rng.choice(pos, k, replace=False).tolist() + rng.choice(neg, min(len(neg), n - k),
                                                                          replace=False).tolist())


@register_calibration("rope_verifier")
def calibration_feeds(n: int, seed: int, spec: Any, data: DataSource | None = None
                      ) -> list[dict[str, np.ndarray]]:
    """``n`` band feeds for int8 calibration."""
    b = data.arrays if isinstance(data, BankSource) else None
    return [{"patch": _feed(b, k, None, None)[None], "side": b["side"][k][None]} for k in _eval_bands(n, seed, data)]


@register_eval("rope_verifier")
def evaluate(predict: Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]], n: int, seed: int,
             spec: Any, data: DataSource | None = None) -> dict[str, float]:
    """AUC over up to ``n`` bands of the validation banks (a third on the rope)."""
    idx = _eval_bands(n, seed, data)
    b = data.arrays
    z = np.array([float(predict({"patch": _feed(b, k, None, None)[None], "side": b["side"][k][None]})["logit"][0, 0])
                  for k in idx])
    return {"auc": binary_auc(z, b["label"][idx].astype(np.int64)), "n": float(len(idx))}
