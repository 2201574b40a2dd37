"""Training of the rope finder: ``dbh train rope_finder``.

Examples are cut once per ``dbh synth`` folder into an ``.npz`` bank by
``python -m monodbh.models.training.rope_finder_bank FOLDER OUT.npz`` (tiles of the photo with the
rope's pixels as the target, see that module). Training draws ``crop`` x ``crop`` windows from
the bank's tiles (even offsets, so the target's 2 x 2 cells stay aligned), half of them from
tiles holding the rope, with photometric augmentation and mirror flips. Loss: binary cross-entropy
per output pixel, the rope's pixels weighted ``pos_weight``, the ring of output pixels next to
the rope not counted (the rope's edge is a matter of anti-aliasing).

Validation (:func:`tile_metrics`): ``tile_auc``, the AUC of a tile's highest logit for "the
tile holds rope" (what the pipeline's decision sees), and the pixel recall / precision at
log-odds 0.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Any, Callable

import cv2
import numpy as np
import torch
from torch.nn import functional as F

from monodbh.models.modeling.registry import build
from monodbh.models.runtime.common import normalize_rgb
from monodbh.models.runtime.rope_finder import RopeFinderConfig
from monodbh.models.training.common import (AugmentConfig, BankSource, DataSource, bank_run_sources,
                                            bank_source, binary_auc, config_from_dict, photometric,
                                            register_calibration, register_eval, select_device, train_loop,
                                            warmup_cosine)

__all__ = ["RopeFinderTrainConfig", "tile_metrics", "train_rope_finder"]

#: tiles' border (photo pixels) not scored: the runtime keeps only the middle of each tile
EVAL_BORDER: int = RopeFinderConfig().border_px


@dataclass
class RopeFinderTrainConfig:
    """Hyper-parameters of :func:`train_rope_finder` (stored in config.json)."""

    size: str = "base"
    seed: int = 0
    batch_size: int = 24
    crop: int = 128                 #: training window side (photo pixels, even)
    lr: float = 3e-3
    weight_decay: float = 1e-4
    warmup_steps: int = 100
    pos_frac: float = 0.5           #: share of windows cut from tiles that hold the rope
    pos_weight: float = 4.0         #: loss weight of rope pixels
    threads: int | None = None
    log_every: int = 50
    val_every: int = 500
    ckpt_every: int = 250
    augment: dict[str, Any] = field(default_factory=lambda: dict(
        hflip=0.5, brightness=0.3, contrast=0.3, saturation=0.3, hue_deg=6.0, blur=0.25,
        blur_sigma=(0.3, 0.9), noise_std=3.0))

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "RopeFinderTrainConfig":
        return config_from_dict(cls, d, "rope_finder")


# --------------------------------------------------------------------------- metrics


def tile_metrics(z: np.ndarray, target: np.ndarray, border: int = EVAL_BORDER // 2) -> dict[str, float]:
    """Metrics of logits ``z`` (N, h, w) against targets (N, h, w) (output pixels).

    ``tile_auc``: a tile's highest logit (border ``border`` output pixels left out) as the score
    of "the tile holds rope"; ``recall`` / ``precision`` of output pixels at log-odds 0 (a
    predicted pixel counts as right within one pixel of the rope).
    """
    b = border
    zc, tc = z[:, b:-b, b:-b], target[:, b:-b, b:-b] > 0
    has = tc.reshape(len(tc), -1).any(1)
    out = {"n": float(len(z)), "n_rope_tiles": float(has.sum()),
           "tile_auc": binary_auc(zc.reshape(len(zc), -1).max(1), has.astype(np.int64))}
    pred = zc > 0
    k = np.ones((3, 3), np.uint8)
    near = np.stack([cv2.dilate(t.astype(np.uint8), k) > 0 for t in tc])
    npred = pred.sum()
    out["recall"] = float((pred & tc).sum() / max(tc.sum(), 1))
    out["precision"] = float((pred & near).sum() / max(npred, 1))
    return out


# --------------------------------------------------------------------------- training


def _window(bank: dict[str, np.ndarray], k: int, crop: int, rng: np.random.Generator | None,
            aug: AugmentConfig | None) -> tuple[np.ndarray, np.ndarray]:
    rgb, t = bank["rgb"][k], bank["target"][k]
    T = rgb.shape[0]
    if crop < T:
        if rng is None:
            o = (T - crop) // 4 * 2
            x0 = y0 = o
        elif t.any() and rng.random() < 0.9:
            # keep some of the rope in the window
            ys, xs = np.nonzero(t)
            j = int(rng.integers(len(xs)))

            def corner(c: int) -> int:
                lo, hi = max(0, 2 * c - crop + 16), min(T - crop, 2 * c - 16)
                v = int(rng.integers(lo, hi + 1)) if hi >= lo else int(np.clip(2 * c - crop // 2, 0, T - crop))
                return v // 2 * 2

            x0, y0 = corner(int(xs[j])), corner(int(ys[j]))
        else:
            x0 = int(rng.integers(0, (T - crop) // 2 + 1)) * 2
            y0 = int(rng.integers(0, (T - crop) // 2 + 1)) * 2
        rgb = rgb[y0:y0 + crop, x0:x0 + crop]
        t = t[y0 // 2:(y0 + crop) // 2, x0 // 2:(x0 + crop) // 2]
    if rng is not None:
        rgb = photometric(rgb, rng, aug)
        if rng.random() < aug.hflip:
            rgb, t = rgb[:, ::-1], t[:, ::-1]
    return normalize_rgb(np.ascontiguousarray(rgb)), np.ascontiguousarray(t)


def _bank_source(data: Any) -> BankSource:
    return bank_source(data, "dbh train rope_finder needs --data (.npz banks of monodbh.models.training.rope_finder_bank)",
                       "dbh train rope_finder: --data must be rope-finder .npz banks", key="target")


def pixel_loss(z: torch.Tensor, t: torch.Tensor, pos_weight: float) -> torch.Tensor:
    """BCE of logits ``z`` (B, 1, h, w) on targets ``t`` (B, h, w) {0, 1}; the ring next to the rope not counted."""
    t = t[:, None].float()
    ring = F.max_pool2d(t, 3, stride=1, padding=1) - t
    w = torch.where(t > 0, torch.full_like(t, pos_weight), 1.0 - ring)
    return (F.binary_cross_entropy_with_logits(z, t, reduction="none") * w).sum() / w.sum().clamp_min(1.0)


def train_rope_finder(run_dir: str, steps: int = 3000, data: Any = None, resume: bool = False, *,
                  val_data: Any = None, stop_at: int | None = None, verbose: bool = True,
                  init_weights: str | None = None, **options: Any) -> dict[str, Any]:
    """Train the rope finder into ``run_dir`` (``dbh train rope_finder``).

    Parameters
    ----------
    run_dir, steps, resume, stop_at, init_weights : as the other ``dbh train`` kinds.
    data : ``.npz`` bank(s) to train on (``monodbh.models.training.rope_finder_bank``).
    val_data : bank(s) for validation (default: none, only the training loss is logged).
    **options : fields of :class:`RopeFinderTrainConfig`.

    Returns
    -------
    dict ``{"step", "val", "bank"}``.
    """
    options, src, vsrc = bank_run_sources(run_dir, resume, options, data, val_data, _bank_source)
    cfg = RopeFinderTrainConfig.from_dict(options)
    if cfg.crop % 2 or cfg.crop < 32:
        raise ValueError(f"rope_finder: crop must be even and >= 32, got {cfg.crop}")
    device = select_device(cfg.threads)
    torch.manual_seed(cfg.seed)
    bank = src.arrays
    vbank = vsrc.arrays if vsrc is not None else None
    has = bank["target"].reshape(len(bank["target"]), -1).any(1)
    pos, neg = np.flatnonzero(has), np.flatnonzero(~has)
    if not len(pos) or not len(neg):
        raise ValueError(f"{src.config()}: the banks need tiles with and without rope")
    if verbose:
        print(f"bank: {len(has)} training tiles ({len(pos)} with rope)"
              + (f", {vsrc.n} validation tiles" if vsrc is not None else ""), flush=True)
    model = build("rope_finder", cfg.size).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)

    sched = warmup_cosine(opt, cfg.warmup_steps, steps)
    aug = AugmentConfig(**{**cfg.augment, "blur_sigma": tuple(cfg.augment.get("blur_sigma", (0.3, 0.9)))})
    timing = {"t": 0.0, "n": 0}
    n_pos = max(1, int(round(cfg.pos_frac * cfg.batch_size)))

    def step_fn(step: int) -> dict[str, float]:
        t0 = time.perf_counter()
        rng = np.random.default_rng([cfg.seed, step, 43])
        idx = np.concatenate([rng.choice(pos, n_pos), rng.choice(neg, cfg.batch_size - n_pos)])
        xs, ts = zip(*(_window(bank, k, cfg.crop, rng, aug) for k in idx))
        x = torch.from_numpy(np.stack(xs)).to(device)
        t = torch.from_numpy(np.stack(ts)).to(device)
        model.train()
        loss = pixel_loss(model(x), t, cfg.pos_weight)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
        opt.step()
        sched.step()
        timing["t"] += time.perf_counter() - t0
        timing["n"] += len(idx)
        return {"loss": float(loss.detach()), "windows_per_s": timing["n"] / max(timing["t"], 1e-9)}

    @torch.no_grad()
    def predict_bank(b: dict[str, np.ndarray]) -> np.ndarray:
        model.eval()
        zs = []
        for k0 in range(0, len(b["target"]), 32):
            x = torch.from_numpy(np.stack([normalize_rgb(r) for r in b["rgb"][k0:k0 + 32]])).to(device)
            zs.append(model(x)[:, 0].cpu().numpy())
        model.train()
        return np.concatenate(zs)

    def validate_fn() -> dict[str, float]:
        if vbank is None:
            return {}
        return tile_metrics(predict_bank(vbank), vbank["target"])

    config = {"kind": "rope_finder", "size": cfg.size, "seed": cfg.seed, "batch_size": cfg.batch_size,
              "train": asdict(cfg), "data": src.config(), "val_data": vsrc.config() if vsrc is not None else None,
              "bank_tiles": int(len(has))}
    res = train_loop(run_dir, init_weights=init_weights, config=config, model=model, optimizer=opt, steps=steps,
                     step_fn=step_fn, validate_fn=validate_fn, resume=resume, scheduler=sched,
                     log_every=cfg.log_every, val_every=cfg.val_every, ckpt_every=cfg.ckpt_every,
                     verbose=verbose, **({"stop_at": stop_at} if stop_at is not None else {}))
    res["bank"] = int(len(has))
    return res


# --------------------------------------------------------------------------- export hooks


def _eval_tiles(n: int, seed: int, data: DataSource | None) -> list[list[int]]:
    """Up to ``n`` mosaics of bank tile indices (each ``k x k`` tiles filling the graph's tile): a
    share with rope as in the bank, drawn at random."""
    if not isinstance(data, BankSource):
        raise ValueError("rope_finder export needs its .npz banks (the run's config.json names them)")
    t = data.arrays["target"]
    rng = np.random.default_rng(seed)
    return [rng.choice(len(t), 4, replace=len(t) < 4).tolist() for _ in range(n)]


def _mosaic(b: dict[str, np.ndarray], ks: list[int], tile: int) -> tuple[np.ndarray, np.ndarray]:
    """A ``tile`` x ``tile`` image of 2 x 2 bank tiles (cropped or padded black) and its target."""
    T = b["rgb"].shape[1]
    img = np.zeros((2 * T, 2 * T, 3), np.uint8)
    tgt = np.zeros((T, T), np.uint8)
    for q, k in enumerate(ks[:4]):
        y, x = divmod(q, 2)
        img[y * T:(y + 1) * T, x * T:(x + 1) * T] = b["rgb"][k]
        tgt[y * T // 2:(y + 1) * T // 2, x * T // 2:(x + 1) * T // 2] = b["target"][k]
    out = np.zeros((tile, tile, 3), np.uint8)
    s = min(tile, 2 * T)
    out[:s, :s] = img[:s, :s]
    to = np.zeros((tile // 2, tile // 2), np.uint8)
    to[:s // 2, :s // 2] = tgt[:s // 2, :s // 2]
    return out, to


def _tile_of(spec: Any) -> int:
    return int(spec.input("image").shape[2])


@register_calibration("rope_finder")
def calibration_feeds(n: int, seed: int, spec: Any, data: DataSource | None = None
                      ) -> list[dict[str, np.ndarray]]:
    """``n`` feeds for int8 calibration: mosaics of 2 x 2 bank tiles at the graph's tile size."""
    b = data.arrays if isinstance(data, BankSource) else None
    return [{"image": normalize_rgb(_mosaic(b, ks, _tile_of(spec))[0])[None]} for ks in _eval_tiles(n, seed, data)]


@register_eval("rope_finder")
def evaluate(predict: Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]], n: int, seed: int,
             spec: Any, data: DataSource | None = None) -> dict[str, float]:
    """Tile AUC and pixel recall / precision over the bank tiles of ``n`` mosaics of the
    validation banks (each mosaic's quadrants scored as the bank's tiles)."""
    b = data.arrays
    T = b["rgb"].shape[1] // 2
    zs, ts = [], []
    for ks in _eval_tiles(n, seed, data):
        img, tgt = _mosaic(b, ks, _tile_of(spec))
        z = predict({"image": normalize_rgb(img)[None]})["logit"][0, 0]
        for q in range(4):
            y, x = divmod(q, 2)
            if (y + 1) * T <= z.shape[0] and (x + 1) * T <= z.shape[1]:
                zs.append(z[y * T:(y + 1) * T, x * T:(x + 1) * T])
                ts.append(tgt[y * T:(y + 1) * T, x * T:(x + 1) * T])
    return tile_metrics(np.stack(zs), np.stack(ts))
