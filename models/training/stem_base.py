"""Training of the stem-base network: ``dbh train stem_base``.

Examples (:func:`tree_strips`): for each stem of an undistorted ``dbh synth`` sample that is in
the photo at 1.3 m (the roped stem first), the strip of :func:`monodbh.models.runtime.stem_base.stem_strip`
is cut from the stem's axis point at 1.3 m, straight down its projected axis, scaled by its
width there (``2 f r / z``). The label is the strip row of the stem's front ground contact
(:func:`monodbh.models.synthetic.stem_base_pixel`) when it is in view and inside the strip, else the
"no visible base" class. In view (:func:`monodbh.models.synthetic.base_in_view`): the stem's front is seen (the ground-truth
depth there is its own) across the front half of the stem at the ground, or anywhere up to
``clutter_height_m`` above it, so that a foot in grass tufts or leaf litter is labelled where it
is, as a person reads it through the clutter; a bush that hides the stem higher up hides the
base (decision record ``docs/decisions/stem-base.md``). Training strips are cut with
the geometry jittered as the pipeline's stem edges err (mid-point 0.1 / 0.3 widths across /
along, width 8 %, direction 2.5 deg), and photometric augmentation and mirror flips on top.

The strips are cut once into an in-memory bank (:func:`build_bank`; a few jittered copies per
stem); training draws batches from it. Size ``effl0`` (EfficientNet-Lite0's ImageNet features,
frozen; the ``pretrained`` extra) draws its photometric augmentation and mirror once per bank
strip, and the backbone's features of the bank are computed once (:func:`bank_features`); only
the decoder trains. Loss: cross-entropy against a Gaussian (1 row) over the
true row, or the no-base class.

Validation (:func:`base_metrics`): ``recall`` (visible bases found within 5 % of the rope-to-
base span, the scale error they give), ``precision`` (found bases that are within it),
``none_acc`` and the spec metric ``score`` (the share of strips answered right: the base
within 5 %, or no base where none is visible).

:func:`ship_net` (``python -m monodbh.models.training.stem_base ship-net RUN``) ships an exported
``effl0`` run as the second stem-base network (``models/stem_base_net_int8.onnx``), which
``StemBaseFinder`` asks where the first network sees no base.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from torch.nn import functional as F

from monodbh.models.modeling.registry import build
from monodbh.models.runtime.stem_base import (STRIP_H, STRIP_ROWS_PER_W, decode_base_logits, stem_strip,
                                         strip_feed)
from monodbh.models.synthetic import base_in_view, stem_base_pixel
from monodbh.models.training.common import (AugmentConfig, DataSource, config_from_dict, held_out_bank,
                                            held_out_split, make_source, photometric, register_calibration,
                                            register_eval, resumed_folder_run, select_device, train_loop,
                                            warmup_cosine)
from monodbh.models.training.depth import undistort_sample
from monodbh.models.training.tree import stem_point_cam

__all__ = ["StemBaseTrainConfig", "stem_geometry", "tree_strips", "build_bank", "bank_features", "base_metrics",
           "train_stem_base"]

#: a found base counts as right within this relative error of the rope-to-base span
GOOD_REL = 0.05


@dataclass
class StemBaseTrainConfig:
    """Hyper-parameters of :func:`train_stem_base` (stored in config.json)."""

    size: str = "base"
    seed: int = 0
    batch_size: int = 64
    lr: float = 2e-3
    weight_decay: float = 1e-4
    warmup_steps: int = 100
    jitters: int = 4               #: jittered strips per stem in the training bank
    max_trees: int = 6             #: stems per sample (the roped one first)
    min_width_px: float = 4.0
    #: a base hidden by clutter lower than this (grass, litter) still counts as in view (m; 0: only
    #: a base seen across the stem's front half)
    clutter_height_m: float = 0.3
    val_n: int = 100               #: samples held out (the source's last ones) when no val data
    label_sigma_rows: float = 1.0
    angle_jitter_deg: float = 2.5  #: 1-sigma of the strip's direction error (the pipeline's: 1.3 deg median, 3.9 q90)
    roped_weight: float = 2.0      #: roped stems are drawn this much more often
    threads: int | None = None
    log_every: int = 20
    val_every: int = 250
    ckpt_every: int = 100
    augment: dict[str, Any] = field(default_factory=lambda: dict(
        hflip=0.5, brightness=0.3, contrast=0.3, saturation=0.3, hue_deg=8.0, blur=0.3,
        blur_sigma=(0.3, 1.2), noise_std=2.0))

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "StemBaseTrainConfig":
        return config_from_dict(cls, d, "stem_base")


# --------------------------------------------------------------------------- ground truth


def _project(K: np.ndarray, p: np.ndarray) -> np.ndarray:
    return np.array([K[0, 0] * p[0] / p[2] + K[0, 2], K[1, 1] * p[1] / p[2] + K[1, 2]])


def stem_geometry(meta: dict[str, Any], tree: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, float, float] | None:
    """``(top_xy, along, width_px, z_m)`` of a stem at 1.3 m in the undistorted photo, or None
    when its axis point there is behind the camera."""
    K = np.asarray(meta["K"], float)
    p13 = stem_point_cam(meta, tree, 1.3)
    p03 = stem_point_cam(meta, tree, 0.3)
    if p13[2] <= 0.3 or p03[2] <= 0.3:
        return None
    top, low = _project(K, p13), _project(K, p03)
    a = low - top
    if np.linalg.norm(a) < 1e-6:
        return None
    r = float(tree.get("r_bh_m", tree["dbh_m"] / 2))
    return top, a / np.linalg.norm(a), 2.0 * K[0, 0] * r / float(p13[2]), float(p13[2])


def _label(top, along, width, base_xy, status) -> float:
    """Strip row of the base (fractional), or -1 for no visible base in the strip."""
    if status != "visible" or base_xy is None:
        return -1.0
    d = np.asarray(base_xy) - top
    row = float(d @ along) / (width / STRIP_ROWS_PER_W)
    off = abs(float(d @ np.array([along[1], -along[0]]))) / width
    if not (2.0 <= row <= STRIP_H - 3) or off > 1.0:
        return -1.0
    return row


def tree_strips(sample: dict[str, Any], rng: np.random.Generator | None, cfg: StemBaseTrainConfig,
                jitters: int = 1) -> list[dict[str, Any]]:
    """Strips and labels of the stems of one (undistorted) sample.

    Returns a list of ``{"strip": (H, W, 3) uint8, "inside": (H, W) bool, "row": float (-1 =
    no base), "roped": bool, "width_px": float}``; ``rng`` None cuts exact (unjittered) strips.
    """
    meta, depth, rgb = sample["meta"], sample.get("depth"), sample["rgb"]
    Himg, Wimg = rgb.shape[:2]
    roped = meta.get("roped_tree")
    trees = sorted(meta["trees"], key=lambda t: (t["id"] != roped, t.get("distance_m", 1e9)))
    out: list[dict[str, Any]] = []
    n_trees = 0
    for tree in trees:
        if n_trees >= cfg.max_trees:
            break
        g = stem_geometry(meta, tree)
        if g is None:
            continue
        top, along, width, z = g
        if width < cfg.min_width_px or not (0 <= top[0] < Wimg and 0 <= top[1] < Himg):
            continue
        u = np.array([along[1], -along[0]])
        if depth is not None:
            # the stem must be what the photo shows across its width at 1.3 m (not hidden, even
            # partly, by a nearer one)
            tol = max(0.3, 0.5 * float(tree["r_bh_m"]) + 0.1)
            pts = [top + f * width * u for f in (-0.3, 0.0, 0.3)]
            if not all(0 <= p[0] < Wimg and 0 <= p[1] < Himg
                       and abs(float(depth[int(p[1]), int(p[0])]) - (z - float(tree["r_bh_m"]))) <= tol
                       for p in pts):
                continue
        bxy, status = stem_base_pixel(meta, tree, depth)
        n_trees += 1
        if status != "outside" and depth is not None:
            status = "visible" if base_in_view(meta, tree, depth, bxy, width, cfg.clutter_height_m) else "occluded"
        for j in range(jitters):
            t_, a_, w_ = top, along, width
            if rng is not None:
                t_ = top + rng.normal(0, 0.1 * width) * u + rng.normal(0, 0.3 * width) * along
                ang = math.radians(rng.normal(0, cfg.angle_jitter_deg))
                c, s = math.cos(ang), math.sin(ang)
                a_ = np.array([c * along[0] - s * along[1], s * along[0] + c * along[1]])
                w_ = width * math.exp(rng.normal(0, 0.08))
            strip, inside = stem_strip(rgb, t_, a_, w_)
            out.append({"strip": strip, "inside": inside, "row": _label(t_, a_, w_, bxy, status),
                        "roped": tree["id"] == roped, "width_px": float(w_), "jit": j,
                        "tree": tree["id"]})
    return out


def build_bank(src: DataSource, indices: list[int], cfg: StemBaseTrainConfig, seed: int,
               jitters: int, verbose: bool = True) -> dict[str, np.ndarray]:
    """Strips of ``indices`` of ``src`` as arrays: ``strip`` (N, H, W, 3) uint8, ``inside``
    (N, H, W) bool, ``row`` (N,) float32, ``roped`` (N,) bool, ``sample`` (N,) int."""
    acc: dict[str, list] = {k: [] for k in ("strip", "inside", "row", "roped", "sample")}
    t0 = time.perf_counter()
    for n, i in enumerate(indices):
        try:
            s = undistort_sample(src.get(i))
        except (OSError, ValueError, KeyError) as e:     # a sample still being written
            if verbose:
                print(f"bank: sample {i} skipped ({e})", flush=True)
            continue
        rng = None if jitters == 0 else np.random.default_rng([seed, i, 17])
        for ex in tree_strips(s, rng, cfg, max(1, jitters)):
            for k in ("strip", "inside", "row", "roped"):
                acc[k].append(ex[k])
            acc["sample"].append(i)
        if verbose and (n + 1) % 100 == 0:
            print(f"bank: {n + 1}/{len(indices)} samples, {len(acc['row'])} strips, "
                  f"{time.perf_counter() - t0:.0f} s", flush=True)
    if not acc["row"]:
        raise RuntimeError(f"no usable stems in {src.config()}")
    return {"strip": np.stack(acc["strip"]), "inside": np.stack(acc["inside"]),
            "row": np.asarray(acc["row"], np.float32), "roped": np.asarray(acc["roped"], bool),
            "sample": np.asarray(acc["sample"], np.int64)}


def _augmented_feed(bank: dict[str, np.ndarray], k: int, rng: np.random.Generator,
                    aug: AugmentConfig) -> np.ndarray:
    """Strip ``k`` of ``bank`` as a network feed ``(4, H, W)``, photometrically augmented and
    mirrored as ``rng`` draws."""
    x = strip_feed(photometric(bank["strip"][k], rng, aug), bank["inside"][k])
    return x[..., ::-1] if rng.random() < aug.hflip else x


def bank_features(model: Any, bank: dict[str, np.ndarray], aug: AugmentConfig, seed: int, batch: int = 64,
                  verbose: bool = True) -> tuple[list[np.ndarray], np.ndarray]:
    """A frozen backbone's features of every bank strip, each augmented once (from ``seed`` and
    its index): ``([(N, C_i, h_i, w_i)] float16, inside (N, 1, H, W) float16)`` for
    ``model.decode``."""
    feats: list[list[np.ndarray]] = []
    inside: list[np.ndarray] = []
    t0 = time.perf_counter()
    N = len(bank["row"])
    for a in range(0, N, batch):
        x = np.stack([_augmented_feed(bank, k, np.random.default_rng([seed, k, 29]), aug)
                      for k in range(a, min(a + batch, N))])
        with torch.no_grad():
            fs = model.features(torch.from_numpy(np.ascontiguousarray(x)))
        feats.append([f.numpy().astype(np.float16) for f in fs])
        inside.append(x[:, 3:].astype(np.float16))
        if verbose and (a // batch) % 20 == 19:
            print(f"features: {a + batch}/{N} strips, {time.perf_counter() - t0:.0f} s", flush=True)
    return [np.concatenate([f[i] for f in feats]) for i in range(len(feats[0]))], np.concatenate(inside)


# --------------------------------------------------------------------------- metrics


def base_metrics(logits: np.ndarray, rows: np.ndarray, threshold: float = 0.5) -> dict[str, float]:
    """Metrics of ``logits`` (N, STRIP_H + 1) against true ``rows`` (N,; -1 = no visible base)."""
    pred = [decode_base_logits(z) for z in logits]
    prow = np.array([p[0] for p in pred])
    pb = np.array([p[1] for p in pred])
    vis = rows >= 0
    found = pb >= threshold
    rel = np.where(vis, np.abs(prow - rows) / np.maximum(rows, 1.0), np.inf)
    good = found & vis & (rel <= GOOD_REL)
    out = {"n": float(len(rows)), "n_visible": float(vis.sum()),
           "recall": float(good[vis].mean()) if vis.any() else 0.0,
           "precision": float(good[found].mean()) if found.any() else 0.0,
           "none_acc": float((~found[~vis]).mean()) if (~vis).any() else 0.0,
           "score": float((good | (~vis & ~found)).mean())}
    if (found & vis).any():
        out["median_rel_err"] = float(np.median(rel[found & vis]))
    return out


# --------------------------------------------------------------------------- training


def _targets(rows: np.ndarray, sigma: float) -> np.ndarray:
    """Soft targets (N, STRIP_H + 1): a Gaussian over the row, or the no-base class."""
    r = np.arange(STRIP_H, dtype=np.float32)
    t = np.zeros((len(rows), STRIP_H + 1), np.float32)
    for k, row in enumerate(rows):
        if row < 0:
            t[k, -1] = 1.0
        else:
            g = np.exp(-0.5 * ((r - row) / sigma) ** 2)
            t[k, :-1] = g / g.sum()
    return t


def _source(data: Any, seed: int) -> DataSource:
    if data is None:
        raise ValueError("dbh train stem_base needs --data (dbh synth folders at 1280x960)")
    return make_source(data, default_seed=seed)


def train_stem_base(run_dir: str, steps: int = 3000, data: Any = None, resume: bool = False, *,
                  val_data: Any = None, stop_at: int | None = None, verbose: bool = True,
                  init_weights: str | None = None, **options: Any) -> dict[str, Any]:
    """Train the stem-base network into ``run_dir`` (``dbh train stem_base``).

    Parameters
    ----------
    run_dir, steps, resume, stop_at, init_weights : as the other ``dbh train`` kinds.
    data : ``dbh synth`` folder(s) (needed: the strips are cut at the photo's resolution).
    val_data : folder(s) for validation; default the last ``val_n`` samples of ``data``, which
        are then left out of training.
    **options : fields of :class:`StemBaseTrainConfig`.

    Returns
    -------
    dict ``{"step", "val", "bank"}``.
    """
    options, data, val_data, train_indices = resumed_folder_run(run_dir, resume, options, data, val_data)
    cfg = StemBaseTrainConfig.from_dict(options)
    device = select_device(cfg.threads)
    torch.manual_seed(cfg.seed)
    src = _source(data, cfg.seed)
    vsrc, train_idx, val_idx = held_out_split(src, None if val_data is None else _source(val_data, cfg.seed + 1),
                                              cfg.val_n, train_indices)
    bank = build_bank(src, train_idx, cfg, cfg.seed, cfg.jitters, verbose)
    vbank = build_bank(vsrc, val_idx, cfg, cfg.seed + 1, 0, verbose)
    if verbose:
        print(f"bank: {len(bank['row'])} training strips ({(bank['row'] >= 0).mean():.1%} with a base), "
              f"{len(vbank['row'])} validation strips", flush=True)
    model = build("stem_base", cfg.size).to(device)
    frozen = hasattr(model, "decode")
    if frozen:
        from monodbh.models.training.pretrained import load_efficientnet_lite0
        load_efficientnet_lite0(model.backbone)       # a resumed run's checkpoint holds the same
        model.backbone.requires_grad_(False)
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=cfg.lr,
                            weight_decay=cfg.weight_decay)

    sched = warmup_cosine(opt, cfg.warmup_steps, steps)
    aug = AugmentConfig(**{**cfg.augment, "blur_sigma": tuple(cfg.augment.get("blur_sigma", (0.3, 1.2)))})
    N = len(bank["row"])
    draw_p = np.where(bank["roped"], cfg.roped_weight, 1.0)
    draw_p = draw_p / draw_p.sum()
    timing = {"t": 0.0, "n": 0}
    cached = bank_features(model, bank, aug, cfg.seed, verbose=verbose) if frozen else None

    def step_fn(step: int) -> dict[str, float]:
        t0 = time.perf_counter()
        rng = np.random.default_rng([cfg.seed, step, 23])
        idx = rng.choice(N, cfg.batch_size, p=draw_p)
        y = torch.from_numpy(_targets(bank["row"][idx], cfg.label_sigma_rows)).to(device)
        if cached is not None:
            z = model.decode([torch.from_numpy(f[idx].astype(np.float32)) for f in cached[0]],
                             torch.from_numpy(cached[1][idx].astype(np.float32)))
        else:
            x = np.stack([_augmented_feed(bank, k, rng, aug) for k in idx])
            z = model(torch.from_numpy(np.ascontiguousarray(x)).to(device))
        loss = -(y * F.log_softmax(z, 1)).sum(1).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
        opt.step()
        sched.step()
        timing["t"] += time.perf_counter() - t0
        timing["n"] += len(idx)
        return {"loss": float(loss.detach()), "strips_per_s": timing["n"] / max(timing["t"], 1e-9)}

    def validate_fn() -> dict[str, float]:
        feeds = np.stack([strip_feed(s, m) for s, m in zip(vbank["strip"], vbank["inside"])])
        zs = []
        for k in range(0, len(feeds), 128):
            with torch.no_grad():
                zs.append(model(torch.from_numpy(feeds[k:k + 128]).to(device)).cpu().numpy())
        z = np.concatenate(zs)
        m = base_metrics(z, vbank["row"])
        r = vbank["roped"]
        if r.any():
            mr = base_metrics(z[r], vbank["row"][r])
            m.update({f"roped_{k}": v for k, v in mr.items()})
        return m

    config = {"kind": "stem_base", "size": cfg.size, "seed": cfg.seed, "batch_size": cfg.batch_size,
              "train": asdict(cfg), "data": src.config(),
              "val_data": vsrc.config() if vsrc is not src else {"type": "same", "indices": val_idx},
              "train_indices": len(train_idx), "bank_strips": int(N)}
    res = train_loop(run_dir, init_weights=init_weights, config=config, model=model, optimizer=opt, steps=steps,
                     step_fn=step_fn, validate_fn=validate_fn, resume=resume, scheduler=sched,
                     log_every=cfg.log_every, val_every=cfg.val_every, ckpt_every=cfg.ckpt_every,
                     verbose=verbose, **({"stop_at": stop_at} if stop_at is not None else {}))
    res["bank"] = int(N)
    return res


# --------------------------------------------------------------------------- export hooks


#: the last evaluation bank cut (``dbh export`` scores every int8 recipe on the same strips)
_EVAL_BANK: dict[str, Any] = {}


def _eval_bank(n: int, seed: int, data: DataSource | None) -> dict[str, np.ndarray]:
    """Up to ``n`` exact strips of the last ``val_n`` samples of ``data`` (the held-out end of
    the folder); unjittered, so ``seed`` does not change them."""
    cfg = StemBaseTrainConfig()
    return held_out_bank(_EVAL_BANK, "stem_base", data, n, cfg.val_n,
                         lambda d, idx: build_bank(d, idx, cfg, seed, 0, verbose=False))


@register_calibration("stem_base")
def calibration_feeds(n: int, seed: int, spec: Any, data: DataSource | None = None
                      ) -> list[dict[str, np.ndarray]]:
    """``n`` strip feeds for int8 calibration."""
    b = _eval_bank(n, seed, data)
    return [{"strip": strip_feed(s, m)[None]} for s, m in zip(b["strip"], b["inside"])]


@register_eval("stem_base")
def evaluate(predict: Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]], n: int, seed: int,
             spec: Any, data: DataSource | None = None) -> dict[str, float]:
    """Base metrics (:func:`base_metrics`) over up to ``n`` exact strips."""
    b = _eval_bank(n, seed, data)
    z = np.concatenate([predict({"strip": strip_feed(s, m)[None]})["logits"] for s, m in zip(b["strip"], b["inside"])])
    return base_metrics(z, b["row"])


# --------------------------------------------------------------------------- the second network


def ship_net(run_dir: str | Any, models_dir: str | Any | None = None) -> dict[str, Any]:
    """Ship the int8 file ``dbh export RUN`` wrote for an ``effl0`` run as the second stem-base
    network (kind ``stem_base_net``, ``models_dir/stem_base_net_int8.onnx``, listed in its
    manifest with the export's scores): ``StemBaseFinder`` asks it where the first sees no
    base. The error model then needs measuring again (``docs/TRAINING.md``)."""
    import onnx

    from monodbh.models.runtime.common import MODELS_DIR, SPEC_METADATA_KEY, load_manifest
    from monodbh.models.training.common import atomic_write_text

    run_dir, models_dir = Path(run_dir), Path(models_dir or MODELS_DIR)
    report = json.loads((run_dir / "export" / "report.json").read_text())
    if report.get("kind") != "stem_base" or report.get("size") != "effl0":
        raise ValueError(f"{run_dir}: not an exported stem_base effl0 run ({report.get('kind')}, {report.get('size')})")
    model = onnx.load(str(run_dir / "export" / "stem_base_int8.onnx"))
    meta = {p.key: p for p in model.metadata_props}
    spec = json.loads(meta[SPEC_METADATA_KEY].value)
    spec["kind"] = "stem_base_net"
    meta[SPEC_METADATA_KEY].value = json.dumps(spec)
    out, tmp = models_dir / "stem_base_net_int8.onnx", models_dir / "stem_base_net_int8.new.onnx"
    onnx.save(model, str(tmp))
    os.replace(tmp, out)
    man_path = models_dir / "manifest.json"
    manifest = load_manifest(man_path)
    io = {k: [{f: t[f] for f in ("dtype", "name", "shape")} for t in spec[k]] for k in ("inputs", "outputs")}
    manifest["models"]["stem_base_net"] = {
        "file": out.name, "sha256": hashlib.sha256(out.read_bytes()).hexdigest(), "spec": spec, **io,
        "extra": spec.get("extra", {}), "precision": "int8", "quant_recipe": report["int8"]["recipe"],
        "latency_ms": {"int8": report["int8"]["latency_ms"], "threads": report.get("threads")},
        "training": {k: report["training"].get(k) for k in ("steps", "size", "data", "seed")},
        "validation": {"int8": report["int8"]["metrics"]}, "exported_at": report.get("exported_at")}
    atomic_write_text(man_path, json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    return {"stem_base_net": str(out), "bytes": out.stat().st_size}


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(prog="python -m monodbh.models.training.stem_base",
                                 description="ship-net RUN: ship an exported effl0 run as the second stem-base network")
    ap.add_argument("command", choices=["ship-net"])
    ap.add_argument("run")
    ap.add_argument("--models-dir", default=None)
    a = ap.parse_args()
    print(ship_net(a.run, a.models_dir))
