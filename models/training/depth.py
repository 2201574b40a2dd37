"""Training of CDEN (conditional depth estimation, Li & Kan 2024 sec. 2.2): ``dbh train depth``.

Data: synthetic samples (``dbh synth`` folders or the on-the-fly generator, rendered without
lens distortion), letterboxed to the network input exactly like
:class:`monodbh.models.runtime.depth.DepthPredictor` does (:func:`depth_example`).  Target: the
canonical log-depth code of the metric z-depth (:func:`monodbh.models.runtime.depth.metric_to_depth_code`
with the sample's focal length at network resolution); sky (depth 0) and letterbox padding are
masked out of every loss.

Losses (generator): ``lambda_gan * BCE(D(x, G(x)), 1) + lambda_l1 * L1(code)`` (the paper's
cGAN + 10 x L1) plus the optional scale-invariant log loss (``lambda_silog``) and the multi-scale
gradient-matching loss on log depth (``lambda_grad``).  The discriminator sees the code with
invalid pixels replaced by +1 for both real and fake maps (no signal from sky/padding).

Validation: AbsRel, SqRel, RMSE, RMSE-log, log10, delta < 1.25^k on metric depth, plus the same
after per-image median scaling (``ms_`` prefix).
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Callable

import cv2
import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from monodbh.models.modeling.cden import (_LN_RANGE, build_cden_discriminator)
from monodbh.models.modeling.registry import build
from monodbh.models.runtime.depth import (letterbox, metric_to_depth_code,
                                        normalize_rgb, depth_code_to_metric)
from monodbh.models.training.common import (AugmentConfig, DataSource, GeneratorSource,
                                            augment, batch_indices, make_source,
                                            register_calibration, register_eval, sample_rng,
                                            select_device, train_loop)
from monodbh.models.training.depth_metrics import depth_metrics

__all__ = ["DepthTrainConfig", "undistort_sample", "depth_example",
           "depth_losses", "silog_loss", "gradient_loss", "train_depth", "default_source",
           "pick_indices", "calibration_feeds", "evaluate"]

#: Default render size of generator samples (landscape 4:3; ``portrait_frac`` of them rotated).
RENDER_SIZE = (256, 192)


@dataclass
class DepthTrainConfig:
    """Hyper-parameters of :func:`train_depth` (all stored in config.json)."""

    size: str = "base"
    seed: int = 0
    batch_size: int = 4
    lr_g: float = 3e-4
    lr_d: float = 1e-4
    d_optim: str = "adam"          #: "adam" (beta1 0.5) or "sgd" (paper: lr 1e-3, momentum 0.99)
    weight_decay: float = 0.01     #: AdamW decay of the generator (transformer)
    warmup_steps: int = 200
    decay_at: float = 0.8          #: lr x0.1 after this fraction of the steps
    lambda_l1: float = 10.0
    lambda_gan: float = 1.0        #: 0 disables the discriminator entirely
    lambda_silog: float = 2.0      #: measured to help (300-step proxy: AbsRel 0.350 -> 0.337
    lambda_grad: float = 2.0       #: and delta1 0.476 -> 0.497 together with lambda_grad)
    gan_start: int = 0             #: first step with the adversarial term
    tree_weight: float = 0.0       #: extra L1 weight on tree pixels (the pipeline reads the stem's depth)
    mask_drop: float = 0.1         #: per-tree probability of dropping it from the input mask
    mask_morph: float = 0.3        #: probability of a random 1-px erode/dilate of the input mask
    segmask_prob: float = 0.0      #: probability of feeding the segmenter's mask (``segmask``) instead
    portrait_frac: float = 0.2     #: generator source only: fraction of portrait renders
    max_eval_depth_m: float = 80.0
    val_n: int = 16
    val_every: int = 500
    ckpt_every: int = 100
    log_every: int = 10
    threads: int | None = None
    augment: dict = field(default_factory=lambda: asdict(AugmentConfig(
        # crop w/h relative to the photo's: 0.5 turns a 4:3 landscape into a 2:3 portrait crop
        crop=0.5, crop_min_area=0.5, crop_aspect=(0.5, 1.0))))

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "DepthTrainConfig":
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise TypeError(f"unknown depth training options: {sorted(unknown)}")
        return cls(**d)


# --------------------------------------------------------------------------- data


class _MixedSource(DataSource):
    """Landscape generator source with a deterministic fraction of portrait samples."""

    def __init__(self, seed: int, size: tuple[int, int], portrait_frac: float,
                 pool: int | None = None, cache: int = 0):
        self.land = GeneratorSource(seed, size, {"distortion": False}, pool, cache)
        self.port = GeneratorSource(seed + 7919, (size[1], size[0]), {"distortion": False},
                                    pool, cache)
        self.frac, self.seed, self.size, self.pool = portrait_frac, seed, size, pool

    @property
    def n(self) -> int | None:
        return self.pool

    def __len__(self) -> int:
        return len(self.land)

    def get(self, index: int) -> dict[str, Any]:
        r = np.random.default_rng([self.seed, index, 3]).random()
        return (self.port if r < self.frac else self.land).get(index)

    def config(self) -> dict[str, Any]:
        return {"type": "generator_mixed", "seed": self.seed, "size": list(self.size),
                "portrait_frac": self.frac, "pool": self.pool}


def default_source(seed: int, portrait_frac: float = 0.2, size: tuple[int, int] = RENDER_SIZE,
                   pool: int | None = None, cache: int = 0) -> DataSource:
    """On-the-fly undistorted generator samples (landscape + ``portrait_frac`` portrait)."""
    if portrait_frac > 0:
        return _MixedSource(seed, size, portrait_frac, pool, cache)
    return GeneratorSource(seed, size, {"distortion": False}, pool, cache)


def _source(data: Any, seed: int, portrait_frac: float) -> DataSource:
    if data is None or data == "gen":
        return default_source(seed, portrait_frac)
    if isinstance(data, dict) and data.get("type") == "generator_mixed":
        return default_source(data["seed"], data["portrait_frac"], tuple(data["size"]), data.get("pool"))
    return make_source(data, default_seed=seed, size=RENDER_SIZE)


def _noisy_mask(instance: np.ndarray, rng: np.random.Generator | None, drop: float,
                morph: float) -> np.ndarray:
    m = instance > 0
    if rng is None:
        return m
    if drop > 0:
        ids = np.unique(instance[m])
        gone = ids[rng.random(ids.size) < drop]
        if gone.size:
            m &= ~np.isin(instance, gone)
    if morph > 0 and rng.random() < morph:
        k = np.ones((3, 3), np.uint8)
        op = cv2.erode if rng.random() < 0.5 else cv2.dilate
        m = op(m.astype(np.uint8), k).astype(bool)
    return m


def _K(sample: dict[str, Any]) -> np.ndarray:
    return np.asarray(sample["K"] if "K" in sample else sample["meta"]["K"], np.float64)


_UNDIST_KEYS = ("rgb", "depth", "semantic", "instance", "rope", "z1", "z2", "segmask")


def undistort_sample(sample: dict[str, Any]) -> dict[str, Any]:
    """Remove lens distortion (``meta['dist']``) from all arrays, keeping ``K``.

    The runtime sees undistorted photos; samples rendered with distortion (``dbh synth``
    default) are remapped (rgb bilinear, labels/depths nearest; depths are z values and do not
    change). Samples without distortion are returned unchanged (same object).
    """
    meta = sample.get("meta") or {}
    dist = np.asarray(meta.get("dist") or [0.0] * 5, np.float64)
    if not np.any(np.abs(dist) > 0):
        return sample
    H, W = sample["rgb"].shape[:2]
    K = _K(sample)
    mx, my = cv2.initUndistortRectifyMap(K, dist, None, K, (W, H), cv2.CV_32FC1)
    out = dict(sample)
    for k in _UNDIST_KEYS:
        a = sample.get(k)
        if a is None:
            continue
        interp = cv2.INTER_LINEAR if k == "rgb" else cv2.INTER_NEAREST
        src = a.astype(np.uint8) if a.dtype == bool else a
        r = cv2.remap(src, mx, my, interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        out[k] = r.astype(bool) if a.dtype == bool else r
    out["meta"] = {**meta, "dist": [0.0] * len(dist)}
    return out


def depth_example(sample: dict[str, Any], size: int, rng: np.random.Generator | None = None,
                  aug: AugmentConfig | None = None, mask_drop: float = 0.0,
                  mask_morph: float = 0.0, segmask_prob: float = 0.0) -> dict[str, np.ndarray]:
    """One training/eval example at network resolution ``size`` (letterbox fit).

    Without ``rng``/``aug`` this is exactly the runtime preprocessing (area-resized photo and
    mask). Returns ``image`` (3, S, S) float32, ``mask`` (1, S, S) float32, ``depth`` (1, S, S)
    float32 metres (0 = invalid: sky, padding), ``code`` (1, S, S) float32 (0 where invalid),
    ``valid`` (1, S, S) bool, ``fx_net`` float and ``tree`` (1, S, S) float32 (1 on the
    ground-truth tree pixels: the extra L1 weight of ``tree_weight``).
    """
    sample = undistort_sample(sample)
    H, W = sample["rgb"].shape[:2]
    if rng is not None and aug is not None:
        # crops keep their own aspect ratio (portrait crops teach the portrait letterbox)
        s = augment(sample, rng, aug, (W, H), fit=size)
        rgb, depth, K = s["rgb"], s["depth"], s["K"]
        h, w = rgb.shape[:2]
        if s.get("segmask") is not None and segmask_prob > 0 and rng.random() < segmask_prob:
            mask = np.asarray(s["segmask"], bool)     # what the segmenter gives at run time
        else:
            mask = _noisy_mask(s["instance"], rng, mask_drop, mask_morph)
        scale = size / max(w, h)
        mask_lb = letterbox(mask, size, "nearest")
        tree_lb = letterbox(s["instance"] > 0, size, "nearest")
    else:
        rgb, depth, K = sample["rgb"], sample["depth"], _K(sample)
        scale = size / max(W, H)
        mask_lb = letterbox(sample["instance"] > 0, size, "mask")
        tree_lb = letterbox(sample["instance"] > 0, size, "nearest")
    fx_net = float(K[0, 0]) * scale
    img = normalize_rgb(letterbox(rgb, size, "rgb"))
    d = letterbox(depth.astype(np.float32), size, "nearest")
    valid = d > 0
    code = np.where(valid, metric_to_depth_code(np.where(valid, d, 1.0), fx_net, size), 0.0)
    return {"image": img, "mask": mask_lb.astype(np.float32)[None], "depth": d[None],
            "code": code.astype(np.float32)[None], "valid": valid[None], "fx_net": fx_net,
            "tree": (np.asarray(tree_lb) > 0.5).astype(np.float32)[None]}


def _collate(items: list[dict[str, Any]], device: torch.device) -> dict[str, torch.Tensor]:
    out = {}
    for k in ("image", "mask", "depth", "code", "valid", "tree"):
        out[k] = torch.from_numpy(np.stack([it[k] for it in items])).to(device)
    out["fx_net"] = torch.tensor([it["fx_net"] for it in items], dtype=torch.float32, device=device)
    return out


# --------------------------------------------------------------------------- losses / metrics


def _masked_mean(x: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    m = m.to(x.dtype)
    return (x * m).sum() / m.sum().clamp_min(1.0)


def silog_loss(t: torch.Tensor, t_gt: torch.Tensor, valid: torch.Tensor, lam: float = 0.85) -> torch.Tensor:
    """Scale-invariant log loss (Eigen et al.) on codes (a code difference is a log-depth difference)."""
    d = (t - t_gt) * (0.5 * _LN_RANGE)
    m = valid.to(d.dtype)
    n = m.flatten(1).sum(1).clamp_min(1.0)
    mu = (d * m).flatten(1).sum(1) / n
    mu2 = (d * d * m).flatten(1).sum(1) / n
    return torch.sqrt((mu2 - lam * mu * mu).clamp_min(1e-8)).mean()


def gradient_loss(t: torch.Tensor, t_gt: torch.Tensor, valid: torch.Tensor, scales: int = 4) -> torch.Tensor:
    """Multi-scale gradient matching (MiDaS) on the log-depth difference."""
    d = (t - t_gt) * (0.5 * _LN_RANGE)
    m = valid.to(d.dtype)
    total = d.new_zeros(())
    for _ in range(scales):
        d = d * m
        mx = m[..., :, 1:] * m[..., :, :-1]
        my = m[..., 1:, :] * m[..., :-1, :]
        gx = (d[..., :, 1:] - d[..., :, :-1]).abs() * mx
        gy = (d[..., 1:, :] - d[..., :-1, :]).abs() * my
        total = total + (gx.sum() + gy.sum()) / (mx.sum() + my.sum()).clamp_min(1.0)
        d, m = d[..., ::2, ::2], m[..., ::2, ::2]
    return total / scales


def _disc_input(code: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    return torch.where(valid, code, torch.ones_like(code))


def depth_losses(t: torch.Tensor, batch: dict[str, torch.Tensor], cfg: DepthTrainConfig,
                 disc: nn.Module | None = None) -> dict[str, torch.Tensor]:
    """Generator loss terms; ``total`` is their weighted sum."""
    v = batch["valid"]
    err = (t - batch["code"]).abs()
    out = {"l1": _masked_mean(err, v)}
    if cfg.tree_weight:
        # the pipeline reads the stem's depth: tree pixels count 1 + tree_weight times
        w = 1.0 + cfg.tree_weight * batch["tree"]
        out["l1_tree"] = _masked_mean(err, v & (batch["tree"] > 0.5))
        total = cfg.lambda_l1 * (err * w * v).sum() / (w * v).sum().clamp_min(1.0)
    else:
        total = cfg.lambda_l1 * out["l1"]
    if cfg.lambda_silog:
        out["silog"] = silog_loss(t, batch["code"], v)
        total = total + cfg.lambda_silog * out["silog"]
    if cfg.lambda_grad:
        out["grad"] = gradient_loss(t, batch["code"], v)
        total = total + cfg.lambda_grad * out["grad"]
    if disc is not None:
        logit = disc(batch["image"], batch["mask"], _disc_input(t, v))
        out["g_gan"] = F.binary_cross_entropy_with_logits(logit, torch.ones_like(logit))
        total = total + cfg.lambda_gan * out["g_gan"]
    out["total"] = total
    return out


def _mean_metrics(ms: list[dict[str, float]]) -> dict[str, float]:
    ms = [m for m in ms if m]
    if not ms:
        return {}
    keys = dict.fromkeys(k for m in ms for k in m)
    return {k: float(np.mean([m[k] for m in ms if k in m])) for k in keys}


# --------------------------------------------------------------------------- training


def _lr_lambda(warmup: int, decay_step: int) -> Callable[[int], float]:
    def f(s: int) -> float:
        w = min(1.0, (s + 1) / warmup) if warmup > 0 else 1.0
        return w * (0.1 if s >= decay_step else 1.0)
    return f


def train_depth(run_dir: str, steps: int = 20000, data: Any = None, resume: bool = False, *,
                val_data: Any = None, stop_at: int | None = None, verbose: bool = True,
                init_weights: str | None = None, **options: Any) -> dict[str, Any]:
    """Train CDEN into run folder ``out`` (``dbh train depth --steps N --out RUN_DIR``).

    Parameters
    ----------
    run_dir : path
        Run folder (config.json, checkpoint.pt, log.jsonl).
    steps : int
        Total optimiser steps (``resume`` continues up to this number).
    resume : bool
        Continue from ``run_dir/checkpoint.pt``; options are then read from its config.json
        (explicit ``options`` override them).
    stop_at : int, optional
        Stop (checkpointed) after this many total steps; ``resume=True`` continues later.
    data, val_data : data source value (see ``common.make_source``), default the generator
        (undistorted, ``RENDER_SIZE`` landscape + ``portrait_frac`` portrait; validation seed
        ``seed + 10_000``).
    **options : fields of :class:`DepthTrainConfig` (``size``, ``batch_size``, ``lr_g``, ...).

    Returns
    -------
    dict
        ``{"step", "val", "images_per_s"}``.
    """
    from monodbh.models.training.common import RunDir

    out = run_dir
    run = RunDir(out)
    if resume and run.config_path.exists():
        old = run.read_config()
        options = {**old.get("train", {}), **options}
        if data is None and old.get("data", {}).get("type") != "list":
            data = old["data"]
        if val_data is None and old.get("val_data", {}).get("type") not in ("list", "same"):
            val_data = old["val_data"]
    cfg = DepthTrainConfig.from_dict(options)
    device = select_device(cfg.threads)
    torch.manual_seed(cfg.seed)
    src = _source(data, cfg.seed, cfg.portrait_frac)
    if val_data is not None:
        vsrc = _source(val_data, cfg.seed + 10_000, cfg.portrait_frac)
        val_idx = list(range(min(cfg.val_n, vsrc.n or cfg.val_n)))
    elif data is None:
        vsrc = default_source(cfg.seed + 10_000, cfg.portrait_frac)
        val_idx = list(range(cfg.val_n))
    else:  # no held-out set given: the last val_n samples of the training source
        vsrc = src
        val_idx = ([(src.n - 1 - i) % src.n for i in range(min(cfg.val_n, src.n))] if src.n
                   else list(range(10**9, 10**9 + cfg.val_n)))
    gen = build("depth", cfg.size).to(device)
    S = gen.spec.inputs[0].shape[-1]
    disc = build_cden_discriminator(cfg.size).to(device) if cfg.lambda_gan > 0 else None
    opt_g = torch.optim.AdamW(gen.parameters(), lr=cfg.lr_g, betas=(0.9, 0.999),
                              weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt_g, _lr_lambda(cfg.warmup_steps, int(cfg.decay_at * steps)))
    extra: dict[str, Any] = {}
    opt_d = None
    if disc is not None:
        opt_d = (torch.optim.SGD(disc.parameters(), lr=cfg.lr_d, momentum=0.99) if cfg.d_optim == "sgd"
                 else torch.optim.Adam(disc.parameters(), lr=cfg.lr_d, betas=(0.5, 0.999)))
        extra = {"disc": disc, "opt_d": opt_d}
    aug = AugmentConfig(**{**cfg.augment, "crop_aspect": tuple(cfg.augment.get("crop_aspect", (1, 1))),
                           "blur_sigma": tuple(cfg.augment.get("blur_sigma", (0.3, 1.5)))})
    val_cache: list[dict[str, np.ndarray]] = []
    timing = {"t": 0.0, "n": 0, "data": 0.0}

    def step_fn(step: int) -> dict[str, float]:
        t0 = time.perf_counter()
        idx = batch_indices(step, cfg.batch_size, src.n, cfg.seed)
        items = [depth_example(src.get(i), S, sample_rng(cfg.seed, step, j), aug, cfg.mask_drop,
                               cfg.mask_morph, cfg.segmask_prob) for j, i in enumerate(idx)]
        b = _collate(items, device)
        t1 = time.perf_counter()
        use_gan = disc is not None and step >= cfg.gan_start
        t = gen(b["image"], b["mask"])
        logs: dict[str, float] = {}
        if use_gan:
            disc.train()
            opt_d.zero_grad(set_to_none=True)
            real = disc(b["image"], b["mask"], _disc_input(b["code"], b["valid"]))
            fake = disc(b["image"], b["mask"], _disc_input(t.detach(), b["valid"]))
            d_loss = 0.5 * (F.binary_cross_entropy_with_logits(real, torch.ones_like(real))
                            + F.binary_cross_entropy_with_logits(fake, torch.zeros_like(fake)))
            d_loss.backward()
            opt_d.step()
            logs["d_loss"] = float(d_loss.detach())
        losses = depth_losses(t, b, cfg, disc if use_gan else None)
        opt_g.zero_grad(set_to_none=True)
        losses["total"].backward()
        torch.nn.utils.clip_grad_norm_(gen.parameters(), 5.0)
        opt_g.step()
        sched.step()
        timing["t"] += time.perf_counter() - t1
        timing["data"] += t1 - t0
        timing["n"] += len(items)
        logs.update({k: float(v.detach()) for k, v in losses.items()})
        logs["img_per_s"] = timing["n"] / max(timing["t"], 1e-9)   # model compute only
        logs["data_s_per_img"] = timing["data"] / max(timing["n"], 1)
        return logs

    def validate_fn() -> dict[str, float]:
        if not val_cache:
            val_cache.extend(depth_example(vsrc.get(i), S) for i in val_idx)
        ms = []
        for k in range(0, len(val_cache), 4):
            items = val_cache[k:k + 4]
            b = _collate(items, device)
            t = gen(b["image"], b["mask"]).cpu().numpy()
            for it, tt in zip(items, t):
                pred = depth_code_to_metric(tt[0], it["fx_net"], S)
                m = depth_metrics(pred, it["depth"][0], it["valid"][0], cfg.max_eval_depth_m)
                # the same on tree pixels alone (what the pipeline reads)
                mt = depth_metrics(pred, it["depth"][0], it["valid"][0] & (it["tree"][0] > 0.5),
                                   cfg.max_eval_depth_m)
                m.update({"tree_absrel": mt["absrel"], "tree_rmse_log": mt["rmse_log"]} if mt else {})
                ms.append(m)
        res = _mean_metrics(ms)
        b = _collate(val_cache[:4], device)
        res["val_l1"] = float(_masked_mean((gen(b["image"], b["mask"]) - b["code"]).abs(), b["valid"]))
        return res

    config = {"kind": "depth", "size": cfg.size, "seed": cfg.seed, "batch_size": cfg.batch_size,
              "train": asdict(cfg), "data": src.config(),
              "val_data": vsrc.config() if vsrc is not src else {"type": "same", "indices": val_idx},
              "input_size": S}
    res = train_loop(out, init_weights=init_weights, config=config, model=gen, optimizer=opt_g, steps=steps,
                     step_fn=step_fn, validate_fn=validate_fn, resume=resume, scheduler=sched,
                     extra=extra, log_every=cfg.log_every, val_every=cfg.val_every,
                     ckpt_every=cfg.ckpt_every, verbose=verbose,
                     **({"stop_at": stop_at} if stop_at is not None else {}))
    res["images_per_s"] = timing["n"] / timing["t"] if timing["t"] else None
    res["data_s_per_image"] = timing["data"] / timing["n"] if timing["n"] else None
    return res


# --------------------------------------------------------------------------- export hooks


def _eval_source(data: Any, seed: int) -> DataSource:
    if data is not None:
        return data if isinstance(data, DataSource) else make_source(data, default_seed=seed)
    # photo-like resolution: the letterbox downsizing path of the runtime is exercised
    return GeneratorSource(seed + 20_000, (512, 384), {"distortion": False})


def pick_indices(src: DataSource, n: int, seed: int) -> list[int]:
    """``n`` sample indices of ``src`` chosen by ``seed`` (calibration and evaluation differ)."""
    if src.n:
        perm = np.random.default_rng([seed, 13]).permutation(src.n)
        return [int(perm[i % src.n]) for i in range(n)]
    return [seed * 100_003 % 2**30 + i for i in range(n)]


@register_calibration("depth")
def calibration_feeds(n: int, seed: int, spec: Any, data: DataSource | None = None
                      ) -> list[dict[str, np.ndarray]]:
    """``n`` runtime-preprocessed input feeds (``image``, ``mask``) for int8 calibration."""
    src = _eval_source(data, seed)
    S = spec.inputs[0].shape[-1]
    feeds = []
    for i in pick_indices(src, n, seed):
        ex = depth_example(src.get(i), S)
        feeds.append({"image": ex["image"][None], "mask": ex["mask"][None]})
    return feeds


@register_eval("depth")
def evaluate(predict: Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]], n: int, seed: int,
             spec: Any, data: DataSource | None = None) -> dict[str, float]:
    """Depth metrics (mean over ``n`` samples) of a predictor; includes ``delta1`` (spec metric)."""
    src = _eval_source(data, seed)
    S = spec.inputs[0].shape[-1]
    ms = []
    for i in pick_indices(src, n, seed):
        ex = depth_example(src.get(i), S)
        t = predict({"image": ex["image"][None], "mask": ex["mask"][None]})["depth_code"][0, 0]
        ms.append(depth_metrics(depth_code_to_metric(t, ex["fx_net"], S), ex["depth"][0], ex["valid"][0]))
    return _mean_metrics(ms)
