"""Training of the stem-edge network: ``dbh train stem_edge``.

Examples (:func:`tree_patches`): for each stem of an undistorted ``dbh synth`` sample (the roped
one at 1.3 m, the others at a random height of 1.0-1.7 m), the stem's cross-section there (the
generator's ellipse and harmonics, taper and flare) is projected into the photo; its two extreme
points across the stem's image direction are the silhouette's edges, the label. A stem counts
only where the photo shows both edges as the stem's own: just inside each edge the
ground-truth depth is the stem's, and just outside it nothing nearer hides it. The patch of
:func:`monodbh.models.runtime.stem_edge.edge_patch` is cut with the geometry jittered as the
pipeline's rough edges err (centre 0.1 widths across, 0.05 along, width 12 %, direction 2 deg),
with photometric augmentation and mirror flips on top.

The patches are cut once into an in-memory bank (:func:`build_bank`); training draws batches
from it. Loss: cross-entropy of each edge's column softmax against a Gaussian (1 column) over
the true column.

Validation (:func:`edge_metrics`): the width between the two predicted edges against the true
one (``width_median_pct``, ``width_p90_pct``), the edges' column errors, and the spec metric
``score``, the share of patches whose width is within 2 %.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from typing import Any, Callable

import numpy as np
import torch
from torch.nn import functional as F

from monodbh.models.modeling.registry import build
from monodbh.models.runtime.stem_edge import PATCH_W, decode_edge_logits, edge_patch, patch_feed, patch_geometry
from monodbh.models.training.common import (AugmentConfig, DataSource, config_from_dict, held_out_bank,
                                            held_out_split, make_source, photometric, register_calibration,
                                            register_eval, resumed_folder_run, select_device, train_loop,
                                            warmup_cosine)
from monodbh.models.training.depth import undistort_sample

__all__ = ["StemEdgeTrainConfig", "stem_edges_truth", "tree_patches", "build_bank", "edge_metrics",
           "train_stem_edge"]

#: a predicted width counts as right within this relative error (the spec metric)
GOOD_REL = 0.02


@dataclass
class StemEdgeTrainConfig:
    """Hyper-parameters of :func:`train_stem_edge` (stored in config.json)."""

    size: str = "base"
    seed: int = 0
    batch_size: int = 64
    lr: float = 2e-3
    weight_decay: float = 1e-4
    warmup_steps: int = 100
    jitters: int = 4               #: jittered patches per stem in the training bank
    max_trees: int = 8             #: stems per sample (the roped one first)
    min_width_px: float = 6.0
    val_n: int = 60                #: samples held out (the source's last ones) when no val data
    label_sigma_cols: float = 1.0
    centre_jitter: float = 0.1     #: 1-sigma of the patch centre's error across the stem (widths)
    width_jitter: float = 0.12     #: 1-sigma of the log rough width's error
    angle_jitter_deg: float = 2.0
    roped_weight: float = 2.0      #: roped stems are drawn this much more often
    threads: int | None = None
    log_every: int = 50
    val_every: int = 500
    ckpt_every: int = 250
    augment: dict[str, Any] = field(default_factory=lambda: dict(
        hflip=0.5, brightness=0.3, contrast=0.3, saturation=0.3, hue_deg=8.0, blur=0.3,
        blur_sigma=(0.3, 1.2), noise_std=2.0))

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "StemEdgeTrainConfig":
        return config_from_dict(cls, d, "stem_edge")


# --------------------------------------------------------------------------- ground truth


def _cam(meta: dict[str, Any], P: np.ndarray) -> np.ndarray:
    R = np.asarray(meta["R_world_from_cam"], np.float64)
    t = np.asarray(meta["t_world_from_cam"], np.float64)
    return (np.asarray(P, np.float64) - t) @ R


def _project(K: np.ndarray, Pc: np.ndarray) -> np.ndarray:
    Pc = np.atleast_2d(Pc)
    return np.stack([K[0, 0] * Pc[:, 0] / Pc[:, 2] + K[0, 2], K[1, 1] * Pc[:, 1] / Pc[:, 2] + K[1, 2]], 1)


def stem_edges_truth(meta: dict[str, Any], tree: dict[str, Any], height_m: float, n: int = 720
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """The stem's silhouette at ``height_m`` in the (undistorted) photo.

    Returns
    -------
    ``(center_xy (2,), along (2,), edges (2,), z_m)``: the axis point's pixel, the stem's image
    direction (unit, down the photo), the left and right edges as offsets (pixels) from the
    centre along the patch's ``across`` direction (:func:`~monodbh.models.runtime.stem_edge.patch_geometry`),
    and the axis point's depth; None where the stem is behind the camera there.
    """
    from monodbh.models.synthetic.scene import cross_section_shape, stem_radius_scale

    K = np.asarray(meta["K"], np.float64)
    ax = np.asarray(tree["axis_world"], np.float64)
    ax = ax / np.linalg.norm(ax)
    e1, e2 = np.asarray(tree["e1_world"], np.float64), np.asarray(tree["e2_world"], np.float64)
    pos = np.asarray(tree["position_world"], np.float64)
    A = pos + height_m * ax
    th = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    r = cross_section_shape(th, float(tree["axis_ratio"]), float(tree["ellipse_phase_rad"]), tree.get("harmonics", []))
    r = r * float(stem_radius_scale(height_m, float(tree["r_bh_m"]), float(tree.get("taper", 0.0)),
                                    float(tree.get("flare", 0.0)), float(tree.get("height_m", 1e3))))
    P = A[None] + (r * np.cos(th))[:, None] * e1[None] + (r * np.sin(th))[:, None] * e2[None]
    Pc = _cam(meta, P)
    ends = _cam(meta, np.stack([A, A + 0.2 * ax, A - 0.2 * ax]))
    if Pc[:, 2].min() <= 0.3 or ends[:, 2].min() <= 0.3:
        return None
    c, hi, lo = _project(K, ends)
    along = lo - hi
    if not np.linalg.norm(along) > 1e-6:
        return None
    along = along / np.linalg.norm(along)
    u = patch_geometry(c, along, 1.0)[:, 0]
    u = u / np.linalg.norm(u)
    s = (_project(K, Pc) - c) @ u
    return c, along, np.array([s.min(), s.max()]), float(ends[0, 2])


def _edges_visible(depth: np.ndarray, c: np.ndarray, along: np.ndarray, u: np.ndarray, edges: np.ndarray,
                   z: float, r: float) -> bool:
    """Both edges are the stem's own in the photo: just inside each (1.5 px and 0.1 widths, at
    three heights) the depth is the stem's, just outside (1.5 px) nothing nearer than its front."""
    H, W = depth.shape
    w = float(edges[1] - edges[0])
    for e, inward in ((edges[0], 1.0), (edges[1], -1.0)):
        for dt in (-0.3 * w, 0.0, 0.3 * w):
            for ds, inside in ((1.5, True), (0.1 * w, True), (-1.5, False)):
                p = c + dt * along + (e + inward * ds) * u
                x, y = int(round(p[0])), int(round(p[1]))
                if not (2 <= x < W - 2 and 2 <= y < H - 2):
                    return False
                d = float(depth[y, x])
                if inside and abs(d - z) > r + 0.15:
                    return False
                if not inside and d < z - 0.5 * r:
                    return False
    return True


def _label_cols(A: np.ndarray, c: np.ndarray, u: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(2,) the edges' (fractional) columns in the patch of affine map ``A`` (its middle row)."""
    M = A[:, :2]
    out = []
    for e in edges:
        col, _ = np.linalg.solve(M, c + e * u - A[:, 2])
        out.append(col)
    return np.array(out)


def tree_patches(sample: dict[str, Any], rng: np.random.Generator | None, cfg: StemEdgeTrainConfig,
                 jitters: int = 1) -> list[dict[str, Any]]:
    """Patches and labels of the stems of one (undistorted) sample.

    Returns a list of ``{"patch": (H, W, 3) uint8, "inside": (H, W) bool, "cols": (2,) float,
    "roped": bool}``; ``rng`` None cuts exact (unjittered) patches, the roped stem at 1.3 m and the
    others at 1.3 m too.
    """
    meta, depth, rgb = sample["meta"], sample.get("depth"), sample["rgb"]
    roped = meta.get("roped_tree")
    trees = sorted(meta["trees"], key=lambda t: (t["id"] != roped, t.get("distance_m", 1e9)))
    out: list[dict[str, Any]] = []
    n_trees = 0
    for tree in trees:
        if n_trees >= cfg.max_trees:
            break
        h = 1.3 if (tree["id"] == roped or rng is None) else float(rng.uniform(1.0, 1.7))
        g = stem_edges_truth(meta, tree, h)
        if g is None:
            continue
        c, along, edges, z = g
        width = float(edges[1] - edges[0])
        if width < cfg.min_width_px:
            continue
        u = patch_geometry(c, along, 1.0)[:, 0]
        u = u / np.linalg.norm(u)
        if depth is None or not _edges_visible(depth, c, along, u, edges, z, float(tree["r_bh_m"])):
            continue
        n_trees += 1
        mid = c + 0.5 * (edges[0] + edges[1]) * u
        for j in range(max(1, jitters)):
            c_, a_, w_ = mid, along, width
            if rng is not None:
                c_ = mid + rng.normal(0, cfg.centre_jitter * width) * u + rng.normal(0, 0.05 * width) * along
                ang = math.radians(rng.normal(0, cfg.angle_jitter_deg))
                cs, sn = math.cos(ang), math.sin(ang)
                a_ = np.array([cs * along[0] - sn * along[1], sn * along[0] + cs * along[1]])
                w_ = width * math.exp(rng.normal(0, cfg.width_jitter))
            A = patch_geometry(c_, a_, w_)
            cols = _label_cols(A, c, u, edges)
            if not (1.0 <= cols[0] and cols[1] <= PATCH_W - 2.0):
                continue
            patch, inside = edge_patch(rgb, c_, a_, w_)
            out.append({"patch": patch, "inside": inside, "cols": cols.astype(np.float32),
                        "roped": tree["id"] == roped})
    return out


def build_bank(src: DataSource, indices: list[int], cfg: StemEdgeTrainConfig, seed: int,
               jitters: int, verbose: bool = True) -> dict[str, np.ndarray]:
    """Patches of ``indices`` of ``src`` as arrays: ``patch`` (N, H, W, 3) uint8, ``inside``
    (N, H, W) bool, ``cols`` (N, 2) float32, ``roped`` (N,) bool, ``sample`` (N,) int."""
    acc: dict[str, list] = {k: [] for k in ("patch", "inside", "cols", "roped", "sample")}
    t0 = time.perf_counter()
    for n, i in enumerate(indices):
        try:
            s = undistort_sample(src.get(i))
        except (OSError, ValueError, KeyError) as e:     # a sample still being written
            if verbose:
                print(f"bank: sample {i} skipped ({e})", flush=True)
            continue
        rng = None if jitters == 0 else np.random.default_rng([seed, i, 29])
        for ex in tree_patches(s, rng, cfg, max(1, jitters)):
            for k in ("patch", "inside", "cols", "roped"):
                acc[k].append(ex[k])
            acc["sample"].append(i)
        if verbose and (n + 1) % 100 == 0:
            print(f"bank: {n + 1}/{len(indices)} samples, {len(acc['cols'])} patches, "
                  f"{time.perf_counter() - t0:.0f} s", flush=True)
    if not acc["cols"]:
        raise RuntimeError(f"no usable stems in {src.config()}")
    return {"patch": np.stack(acc["patch"]), "inside": np.stack(acc["inside"]),
            "cols": np.stack(acc["cols"]).astype(np.float32), "roped": np.asarray(acc["roped"], bool),
            "sample": np.asarray(acc["sample"], np.int64)}


# --------------------------------------------------------------------------- metrics


def edge_metrics(logits: np.ndarray, cols: np.ndarray) -> dict[str, float]:
    """Metrics of ``logits`` (N, 2, PATCH_W) against the true ``cols`` (N, 2)."""
    pred = np.stack([decode_edge_logits(z)[0] for z in logits])
    w_true = cols[:, 1] - cols[:, 0]
    w_err = np.abs((pred[:, 1] - pred[:, 0]) / np.maximum(w_true, 1e-6) - 1.0)
    e_err = np.abs(pred - cols)
    return {"n": float(len(cols)), "width_median_pct": float(100 * np.median(w_err)),
            "width_p90_pct": float(100 * np.percentile(w_err, 90)),
            "edge_median_cols": float(np.median(e_err)), "edge_p90_cols": float(np.percentile(e_err, 90)),
            "score": float((w_err <= GOOD_REL).mean())}


# --------------------------------------------------------------------------- training


def _targets(cols: np.ndarray, sigma: float) -> np.ndarray:
    """Soft targets (N, 2, PATCH_W): a Gaussian over each edge's column."""
    c = np.arange(PATCH_W, dtype=np.float32)
    t = np.exp(-0.5 * ((c[None, None] - cols[:, :, None]) / sigma) ** 2)
    return (t / t.sum(2, keepdims=True)).astype(np.float32)


def _source(data: Any, seed: int) -> DataSource:
    if data is None:
        raise ValueError("dbh train stem_edge needs --data (dbh synth folders at 1280x960)")
    return make_source(data, default_seed=seed)


def train_stem_edge(run_dir: str, steps: int = 3000, data: Any = None, resume: bool = False, *,
                    val_data: Any = None, stop_at: int | None = None, verbose: bool = True,
                    init_weights: str | None = None, **options: Any) -> dict[str, Any]:
    """Train the stem-edge network into ``run_dir`` (``dbh train stem_edge``).

    Parameters
    ----------
    run_dir, steps, resume, stop_at, init_weights : as the other ``dbh train`` kinds.
    data : ``dbh synth`` folder(s) (needed: the patches are cut at the photo's resolution).
    val_data : folder(s) for validation; default the last ``val_n`` samples of ``data``, which
        are then left out of training.
    **options : fields of :class:`StemEdgeTrainConfig`.

    Returns
    -------
    dict ``{"step", "val", "bank"}``.
    """
    options, data, val_data, train_indices = resumed_folder_run(run_dir, resume, options, data, val_data)
    cfg = StemEdgeTrainConfig.from_dict(options)
    device = select_device(cfg.threads)
    torch.manual_seed(cfg.seed)
    src = _source(data, cfg.seed)
    vsrc, train_idx, val_idx = held_out_split(src, None if val_data is None else _source(val_data, cfg.seed + 1),
                                              cfg.val_n, train_indices)
    bank = build_bank(src, train_idx, cfg, cfg.seed, cfg.jitters, verbose)
    vbank = build_bank(vsrc, val_idx, cfg, cfg.seed + 1, 0, verbose)
    if verbose:
        print(f"bank: {len(bank['cols'])} training patches ({bank['roped'].mean():.1%} roped), "
              f"{len(vbank['cols'])} validation patches", flush=True)
    model = build("stem_edge", cfg.size).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = warmup_cosine(opt, cfg.warmup_steps, steps)
    aug = AugmentConfig(**{**cfg.augment, "blur_sigma": tuple(cfg.augment.get("blur_sigma", (0.3, 1.2)))})
    N = len(bank["cols"])
    draw_p = np.where(bank["roped"], cfg.roped_weight, 1.0)
    draw_p = draw_p / draw_p.sum()
    timing = {"t": 0.0, "n": 0}

    def step_fn(step: int) -> dict[str, float]:
        t0 = time.perf_counter()
        rng = np.random.default_rng([cfg.seed, step, 31])
        idx = rng.choice(N, cfg.batch_size, p=draw_p)
        xs, ys = [], []
        for k in idx:
            x = patch_feed(photometric(bank["patch"][k], rng, aug), bank["inside"][k])
            c = bank["cols"][k].copy()
            if rng.random() < aug.hflip:
                x = x[..., ::-1]
                c = np.array([PATCH_W - 1 - c[1], PATCH_W - 1 - c[0]], np.float32)
            xs.append(x)
            ys.append(c)
        x = torch.from_numpy(np.ascontiguousarray(np.stack(xs))).to(device)
        y = torch.from_numpy(_targets(np.stack(ys), cfg.label_sigma_cols)).to(device)
        z = model(x)
        loss = -(y * F.log_softmax(z, 2)).sum(2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
        opt.step()
        sched.step()
        timing["t"] += time.perf_counter() - t0
        timing["n"] += len(idx)
        return {"loss": float(loss.detach()), "patches_per_s": timing["n"] / max(timing["t"], 1e-9)}

    def validate_fn() -> dict[str, float]:
        feeds = np.stack([patch_feed(p, m) for p, m in zip(vbank["patch"], vbank["inside"])])
        zs = []
        for k in range(0, len(feeds), 256):
            zs.append(model(torch.from_numpy(feeds[k:k + 256]).to(device)).cpu().numpy())
        z = np.concatenate(zs)
        m = edge_metrics(z, vbank["cols"])
        r = vbank["roped"]
        if r.any():
            m.update({f"roped_{k}": v for k, v in edge_metrics(z[r], vbank["cols"][r]).items()})
        return m

    config = {"kind": "stem_edge", "size": cfg.size, "seed": cfg.seed, "batch_size": cfg.batch_size,
              "train": asdict(cfg), "data": src.config(),
              "val_data": vsrc.config() if vsrc is not src else {"type": "same", "indices": val_idx},
              "train_indices": len(train_idx), "bank_patches": int(N)}
    res = train_loop(run_dir, init_weights=init_weights, config=config, model=model, optimizer=opt, steps=steps,
                     step_fn=step_fn, validate_fn=validate_fn, resume=resume, scheduler=sched,
                     log_every=cfg.log_every, val_every=cfg.val_every, ckpt_every=cfg.ckpt_every,
                     verbose=verbose, **({"stop_at": stop_at} if stop_at is not None else {}))
    res["bank"] = int(N)
    return res


# --------------------------------------------------------------------------- export hooks


#: the last evaluation bank cut (``dbh export`` scores every int8 recipe on the same patches)
_EVAL_BANK: dict[str, Any] = {}


def _eval_bank(n: int, seed: int, data: DataSource | None) -> dict[str, np.ndarray]:
    """Up to ``n`` exact patches of the last ``val_n`` samples of ``data`` (the held-out end of
    the folder); unjittered, so ``seed`` does not change them."""
    cfg = StemEdgeTrainConfig()
    return held_out_bank(_EVAL_BANK, "stem_edge", data, n, cfg.val_n,
                         lambda d, idx: build_bank(d, idx, cfg, seed, 0, verbose=False))


@register_calibration("stem_edge")
def calibration_feeds(n: int, seed: int, spec: Any, data: DataSource | None = None
                      ) -> list[dict[str, np.ndarray]]:
    """``n`` patch feeds for int8 calibration."""
    b = _eval_bank(n, seed, data)
    return [{"patch": patch_feed(p, m)[None]} for p, m in zip(b["patch"], b["inside"])]


@register_eval("stem_edge")
def evaluate(predict: Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]], n: int, seed: int,
             spec: Any, data: DataSource | None = None) -> dict[str, float]:
    """Edge metrics (:func:`edge_metrics`) over up to ``n`` exact patches."""
    b = _eval_bank(n, seed, data)
    z = np.concatenate([predict({"patch": patch_feed(p, m)[None]})["logits"] for p, m in zip(b["patch"], b["inside"])])
    return edge_metrics(z, b["cols"])
