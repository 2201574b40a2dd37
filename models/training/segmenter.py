"""Training of the Mask2Former-style segmenter (kind ``"segmenter"``).

* Targets (:func:`build_targets`): every tree instance (``instance == k``) is a "thing" mask of
  class tree; each stuff class present (sky, ground, other vegetation, other; pixels with
  ``instance == 0``) is one mask. Masks are area-downsampled to the mask resolution (soft
  targets in [0, 1]).
* Loss (:class:`SetCriterion`): Mask2Former recipe - Hungarian matching per image and per
  decoder layer (``scipy.optimize.linear_sum_assignment``) on ``2 * class cost + 5 * sigmoid BCE
  + 5 * dice`` (full mask resolution, or ``num_points`` random points), cross-entropy with
  no-object weight 0.1, BCE + dice on matched masks normalised by the number of target masks,
  deep supervision on every prediction (initial queries + each decoder layer).
* Metrics (:func:`evaluate_segmenter`): roped-tree instance IoU (GT ``instance ==
  meta['roped_tree']`` vs best predicted tree segment) and panoptic quality (PQ, SQ, RQ) for
  things (tree) and stuff, computed on the *runtime* inference path (``preprocess_image`` ->
  network -> :func:`monodbh.models.runtime.segmenter.panoptic_merge` at the photo's resolution), so
  validation, export gating and the shipped model agree.
* :func:`train_segmenter` - the resumable training loop (``training.common.train_loop``).
* Export hooks: calibration inputs and the task metric (``roped_iou``) for ``dbh export``.
"""
from __future__ import annotations

import math
import os
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable, Sequence

import cv2
import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from torch.nn import functional as F

from monodbh.models.modeling.registry import ModelSpec, build, get_spec
from monodbh.models.modeling.segmenter import CLASSES, TREE_CLASS
from monodbh.models.runtime.common import preprocess_image
from monodbh.models.runtime.segmenter import panoptic_merge
from monodbh.models.training.common import (AugmentConfig, DataSource, GeneratorSource,
                                            augment, batch_indices, make_source,
                                            register_calibration, register_eval, sample_rng,
                                            select_device, train_loop)

__all__ = ["build_targets", "HungarianMatcher", "SetCriterion", "panoptic_quality_stats",
           "evaluate_segmenter", "train_segmenter", "make_batch", "torch_predictor",
           "DEFAULT_VAL_SEED", "STUFF_CLASSES"]

STUFF_CLASSES: tuple[int, ...] = tuple(c for c in range(len(CLASSES)) if c != TREE_CLASS)
#: Generator seed of the default validation set (disjoint from training seeds 0..999).
DEFAULT_VAL_SEED = 1_000_003


# --------------------------------------------------------------------------- targets


def build_targets(semantic: np.ndarray, instance: np.ndarray, mask_size: tuple[int, int],
                  min_area: int = 4, min_thing_area: int = 64) -> dict[str, torch.Tensor]:
    """Set-prediction targets of one image.

    Parameters
    ----------
    semantic : (H, W) uint8
        Semantic ids (0 sky, 1 ground, 2 other vegetation, 3 tree, 4 other).
    instance : (H, W) uint16
        Tree ids (0 = none).
    mask_size : (w, h)
        Mask resolution (network output, 1/4 of the input).
    min_area : int
        Stuff segments with fewer pixels (at the given (H, W)) are dropped.
    min_thing_area : int
        Tree instances with fewer pixels are dropped (not targets: queries predicting them are
        pushed to "no object"). 64 px at 256x256 input = 4 px at mask resolution; synthetic
        scenes have 40-60 trees above that, more than the queries could cover otherwise.

    Returns
    -------
    dict
        ``labels`` (T,) int64, ``masks`` (T, h, w) float32 soft masks.
    """
    labels: list[int] = []
    masks: list[np.ndarray] = []
    ids, counts = np.unique(instance, return_counts=True)
    for k, n in zip(ids, counts):
        if k == 0 or n < max(min_area, min_thing_area):
            continue
        labels.append(TREE_CLASS)
        masks.append(instance == k)
    bg = instance == 0
    for c in STUFF_CLASSES:
        m = (semantic == c) & bg
        if m.sum() >= min_area:
            labels.append(c)
            masks.append(m)
    w, h = mask_size
    if masks:
        arr = np.stack([cv2.resize(m.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
                        for m in masks])
    else:
        arr = np.zeros((0, h, w), np.float32)
    return {"labels": torch.as_tensor(labels, dtype=torch.int64),
            "masks": torch.from_numpy(arr.reshape(len(masks), h, w))}


# --------------------------------------------------------------------------- loss


def _pair_bce(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Mean sigmoid BCE between every prediction row and target row: (Q, N), (T, N) -> (Q, T)."""
    n = x.shape[1]
    pos = F.softplus(-x)  # -log sigmoid(x)
    neg = F.softplus(x)   # -log(1 - sigmoid(x))
    return (pos @ t.T + neg @ (1 - t).T) / n


def _pair_dice(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    p = x.sigmoid()
    num = 2 * p @ t.T
    den = p.sum(-1)[:, None] + t.sum(-1)[None, :]
    return 1 - (num + 1) / (den + 1)


class HungarianMatcher:
    """Mask2Former matcher: ``cost = w_class * (-p[class]) + w_mask * BCE + w_dice * dice``.

    ``num_points=None`` uses every mask pixel; otherwise that many uniformly random points
    (same points for predictions and targets, as in Mask2Former).
    """

    def __init__(self, cost_class: float = 2.0, cost_mask: float = 5.0, cost_dice: float = 5.0,
                 num_points: int | None = None) -> None:
        self.cost_class, self.cost_mask, self.cost_dice = cost_class, cost_mask, cost_dice
        self.num_points = num_points

    @torch.no_grad()
    def __call__(self, cls: torch.Tensor, masks: torch.Tensor,
                 targets: Sequence[dict[str, torch.Tensor]]) -> list[tuple[np.ndarray, np.ndarray]]:
        """``cls`` (B, Q, C+1), ``masks`` (B, Q, h, w) -> per image (query idx, target idx)."""
        out = []
        for b, tgt in enumerate(targets):
            T = len(tgt["labels"])
            if T == 0:
                out.append((np.zeros(0, np.int64), np.zeros(0, np.int64)))
                continue
            prob = cls[b].float().softmax(-1)
            c_cls = -prob[:, tgt["labels"]]
            x = masks[b].flatten(1).float()
            t = tgt["masks"].flatten(1).to(x)
            if self.num_points:
                idx = torch.randint(0, x.shape[1], (self.num_points,), device=x.device)
                x, t = x[:, idx], t[:, idx]
            C = (self.cost_class * c_cls + self.cost_mask * _pair_bce(x, t)
                 + self.cost_dice * _pair_dice(x, t))
            qi, ti = linear_sum_assignment(C.cpu().numpy())
            out.append((qi.astype(np.int64), ti.astype(np.int64)))
        return out


class SetCriterion:
    """Mask2Former loss with deep supervision.

    ``__call__(preds, targets)`` with ``preds`` = ``model.forward_all(images)`` (list of
    ``(class_logits, mask_logits)``) returns ``(total, parts)`` where parts has ``loss_ce``,
    ``loss_mask``, ``loss_dice`` of the final layer and ``loss_aux`` (sum over the others).
    """

    def __init__(self, num_classes: int = len(CLASSES), eos_coef: float = 0.1,
                 w_class: float = 2.0, w_mask: float = 5.0, w_dice: float = 5.0,
                 num_points: int | None = None) -> None:
        self.num_classes = num_classes
        self.matcher = HungarianMatcher(w_class, w_mask, w_dice, num_points)
        self.w_class, self.w_mask, self.w_dice = w_class, w_mask, w_dice
        self.num_points = num_points
        weight = torch.ones(num_classes + 1)
        weight[-1] = eos_coef
        self.empty_weight = weight

    def single(self, cls: torch.Tensor, masks: torch.Tensor,
               targets: Sequence[dict[str, torch.Tensor]], num_masks: float
               ) -> dict[str, torch.Tensor]:
        idx = self.matcher(cls, masks, targets)
        B, Q, _ = cls.shape
        tgt_cls = torch.full((B, Q), self.num_classes, dtype=torch.int64, device=cls.device)
        src_list, tgt_list = [], []
        for b, (qi, ti) in enumerate(idx):
            if len(qi):
                tgt_cls[b, torch.as_tensor(qi, device=cls.device)] = \
                    targets[b]["labels"].to(cls.device)[torch.as_tensor(ti)]
                src_list.append(masks[b, torch.as_tensor(qi, device=cls.device)])
                tgt_list.append(targets[b]["masks"].to(masks)[torch.as_tensor(ti)])
        loss_ce = F.cross_entropy(cls.transpose(1, 2).float(), tgt_cls,
                                  self.empty_weight.to(cls.device))
        if src_list:
            x = torch.cat(src_list).flatten(1).float()
            t = torch.cat(tgt_list).flatten(1)
            if self.num_points:
                pidx = torch.randint(0, x.shape[1], (x.shape[0], self.num_points), device=x.device)
                x, t = x.gather(1, pidx), t.gather(1, pidx)
            loss_mask = F.binary_cross_entropy_with_logits(x, t, reduction="none").mean(1).sum() / num_masks
            p = x.sigmoid()
            dice = 1 - (2 * (p * t).sum(-1) + 1) / (p.sum(-1) + t.sum(-1) + 1)
            loss_dice = dice.sum() / num_masks
        else:
            loss_mask = masks.sum() * 0.0
            loss_dice = masks.sum() * 0.0
        return {"loss_ce": loss_ce, "loss_mask": loss_mask, "loss_dice": loss_dice}

    def __call__(self, preds: Sequence[tuple[torch.Tensor, torch.Tensor]],
                 targets: Sequence[dict[str, torch.Tensor]]
                 ) -> tuple[torch.Tensor, dict[str, float]]:
        num_masks = max(float(sum(len(t["labels"]) for t in targets)), 1.0)
        total = 0.0
        parts: dict[str, float] = {}
        aux = 0.0
        for i, (cls, masks) in enumerate(preds):
            d = self.single(cls, masks, targets, num_masks)
            layer = self.w_class * d["loss_ce"] + self.w_mask * d["loss_mask"] + self.w_dice * d["loss_dice"]
            total = total + layer
            if i == len(preds) - 1:
                parts.update({k: float(v.detach()) for k, v in d.items()})
            else:
                aux += float(layer.detach())
        parts["loss_aux"] = aux
        parts["loss"] = float(total.detach())
        return total, parts


# --------------------------------------------------------------------------- metrics


def _gt_segments(semantic: np.ndarray, instance: np.ndarray, min_area: int
                 ) -> tuple[np.ndarray, list[tuple[int, int]], np.ndarray]:
    """GT panoptic map (H, W) int32, [(id, label)], void mask (tiny segments)."""
    gt = np.zeros(semantic.shape, np.int32)
    void = np.zeros(semantic.shape, bool)
    segs: list[tuple[int, int]] = []
    nid = 1
    ids, counts = np.unique(instance, return_counts=True)
    for k, n in zip(ids, counts):
        if k == 0:
            continue
        m = instance == k
        if n < min_area:
            void |= m
            continue
        gt[m] = nid
        segs.append((nid, TREE_CLASS))
        nid += 1
    bg = instance == 0
    for c in STUFF_CLASSES:
        m = (semantic == c) & bg
        n = int(m.sum())
        if n == 0:
            continue
        if n < min_area:
            void |= m
            continue
        gt[m] = nid
        segs.append((nid, c))
        nid += 1
    void |= (gt == 0) & ~void & (semantic == TREE_CLASS)  # tree pixels without an instance id
    return gt, segs, void


def panoptic_quality_stats(pred: np.ndarray, pred_segments: Sequence[dict[str, Any]],
                           semantic: np.ndarray, instance: np.ndarray,
                           num_classes: int = len(CLASSES), min_area: int = 32) -> np.ndarray:
    """Per-class PQ accumulators of one image: ``(num_classes, 4)`` = IoU sum, TP, FP, FN.

    Standard PQ matching (same class, IoU > 0.5). GT segments smaller than ``min_area`` pixels
    are void: predictions lying more than half in void are not false positives.
    """
    gt, gsegs, void = _gt_segments(semantic, instance, min_area)
    stats = np.zeros((num_classes, 4), np.float64)
    G = gt.max() + 1
    P = int(pred.max()) + 1 if pred.size else 1
    joint = np.bincount((gt.astype(np.int64) * P + pred).ravel(), minlength=G * P).reshape(G, P)
    gt_area = joint.sum(1)
    pred_area = joint.sum(0)
    void_pred = np.bincount(pred[void].ravel(), minlength=P) if void.any() else np.zeros(P, np.int64)
    plabel = {s["id"]: s["label"] for s in pred_segments}
    matched_p: set[int] = set()
    matched_g: set[int] = set()
    for gid, glab in gsegs:
        for pid in np.nonzero(joint[gid])[0]:
            if pid == 0 or plabel.get(int(pid)) != glab:
                continue
            inter = joint[gid, pid]
            union = gt_area[gid] + pred_area[pid] - inter - void_pred[pid]
            iou = inter / max(union, 1)
            if iou > 0.5:
                stats[glab, 0] += iou
                stats[glab, 1] += 1
                matched_p.add(int(pid))
                matched_g.add(gid)
                break
    for gid, glab in gsegs:
        if gid not in matched_g:
            stats[glab, 3] += 1
    for s in pred_segments:
        pid = s["id"]
        if pid in matched_p or pid >= P:
            continue
        if void_pred[pid] > 0.5 * pred_area[pid]:
            continue
        stats[s["label"], 2] += 1
    return stats


def _pq_from_stats(stats: np.ndarray, classes: Sequence[int]) -> tuple[float, float, float]:
    pqs, sqs, rqs = [], [], []
    for c in classes:
        iou, tp, fp, fn = stats[c]
        if tp + fp + fn == 0:
            continue
        sq = iou / tp if tp else 0.0
        rq = tp / (tp + 0.5 * fp + 0.5 * fn)
        pqs.append(sq * rq)
        sqs.append(sq)
        rqs.append(rq)
    if not pqs:
        return 0.0, 0.0, 0.0
    return float(np.mean(pqs)), float(np.mean(sqs)), float(np.mean(rqs))


def evaluate_segmenter(predict: Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]],
                       samples: Sequence[dict[str, Any]], spec: ModelSpec,
                       score_threshold: float = 0.5, overlap_threshold: float = 0.8,
                       min_area_frac: float = 1e-3) -> dict[str, float]:
    """Metrics of a segmenter on samples, through the runtime inference path.

    GT segments smaller than ``min_area_frac`` of the image (1e-3 = 64 px at 256x256, the
    training threshold for trees) are void. Each sample's ``rgb`` is preprocessed like the runtime, ``predict`` gives
    ``class_logits``/``mask_logits``, :func:`~monodbh.models.runtime.segmenter.panoptic_merge` produces
    segments at the sample's resolution, compared with ``semantic``/``instance``.

    Returns
    -------
    dict
        ``roped_iou`` (mean over samples with a roped tree), ``roped_detected`` (fraction with
        IoU > 0.5), ``pq``, ``sq``, ``rq`` (all classes), ``pq_things``, ``pq_stuff``,
        ``n_roped``, ``n``.
    """
    pre = asdict(spec.preprocess[0])
    shape = spec.input("image").shape
    stats = np.zeros((len(CLASSES), 4))
    ious: list[float] = []
    for s in samples:
        rgb = s["rgb"]
        H, W = rgb.shape[:2]
        out = predict({"image": preprocess_image(rgb, pre, shape)})
        res = panoptic_merge(out["class_logits"][0], out["mask_logits"][0], (W, H), (TREE_CLASS,),
                             score_threshold, overlap_threshold)
        pan = res["panoptic"]
        min_area = max(1, int(round(min_area_frac * H * W)))
        stats += panoptic_quality_stats(pan, res["segments"], s["semantic"], s["instance"],
                                        min_area=min_area)
        rid = (s.get("meta") or {}).get("roped_tree")
        if rid:
            gtm = s["instance"] == rid
            if gtm.any():
                best = 0.0
                for seg in res["segments"]:
                    if seg["label"] != TREE_CLASS:
                        continue
                    pm = pan == seg["id"]
                    inter = np.logical_and(pm, gtm).sum()
                    best = max(best, inter / max(np.logical_or(pm, gtm).sum(), 1))
                ious.append(float(best))
    pq, sq, rq = _pq_from_stats(stats, range(len(CLASSES)))
    pq_th = _pq_from_stats(stats, (TREE_CLASS,))[0]
    pq_st = _pq_from_stats(stats, STUFF_CLASSES)[0]
    return {"roped_iou": float(np.mean(ious)) if ious else 0.0,
            "roped_detected": float(np.mean([i > 0.5 for i in ious])) if ious else 0.0,
            "pq": pq, "sq": sq, "rq": rq, "pq_things": pq_th, "pq_stuff": pq_st,
            "n_roped": float(len(ious)), "n": float(len(samples))}


def torch_predictor(model: torch.nn.Module, device: torch.device | str = "cpu"
                    ) -> Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]]:
    """Wrap a torch segmenter as ``predict(feeds) -> {output: array}`` (eval, no grad)."""

    def predict(feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        model.eval()
        with torch.no_grad():
            c, m = model(torch.from_numpy(feeds["image"]).to(device))
        return {"class_logits": c.float().cpu().numpy(), "mask_logits": m.float().cpu().numpy()}

    return predict


# --------------------------------------------------------------------------- data


def _normalise(rgb: np.ndarray, spec: ModelSpec) -> torch.Tensor:
    p = spec.preprocess[0]
    x = rgb.astype(np.float32) * np.float32(p.scale)
    x = (x - np.asarray(p.mean, np.float32)) / np.asarray(p.std, np.float32)
    return torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1)))


def make_batch(source: DataSource, step: int, batch_size: int, seed: int, spec: ModelSpec,
               aug: AugmentConfig | None, min_area: int = 4, min_thing_area: int = 64
               ) -> tuple[torch.Tensor, list[dict[str, torch.Tensor]]]:
    """Images ``(B, 3, S, S)`` and targets of training step ``step`` (pure function of inputs)."""
    S = spec.input("image").shape[-1]
    M = spec.output("mask_logits").shape[-1]
    imgs, tgts = [], []
    for slot, idx in enumerate(batch_indices(step, batch_size, source.n, seed)):
        s = augment(source.get(idx), sample_rng(seed, step, slot), aug, (S, S))
        imgs.append(_normalise(s["rgb"], spec))
        tgts.append(build_targets(s["semantic"], s["instance"], (M, M), min_area,
                                  int(round(min_thing_area * (S / 256.0) ** 2))))
    return torch.stack(imgs), tgts


def _default_source(seed: int, size: tuple[int, int] = (320, 240)) -> DataSource:
    return GeneratorSource(seed, size)


# --------------------------------------------------------------------------- training


def train_segmenter(run_dir: str | os.PathLike, steps: int = 20000, data: Any = "gen",
                    resume: bool = False, *, size: str = "base", batch_size: int = 8,
                    lr: float = 3e-4, weight_decay: float = 0.05, warmup_steps: int = 250,
                    grad_clip: float = 1.0, seed: int = 0, val_data: Any = None,
                    n_val: int = 32, val_every: int = 500, ckpt_every: int = 200,
                    log_every: int = 20, aug: AugmentConfig | None = None,
                    num_points: int | None = None, min_area: int = 4,
                    min_thing_area: int = 64,
                    gen_size: tuple[int, int] = (320, 240), threads: int | None = None,
                    stop_at: int | None = None, verbose: bool = True,
                    init_weights: str | None = None,
                    backbone_lr_scale: float = 1.0) -> dict[str, Any]:
    """Train the segmenter; resumable (see ``training.common.train_loop``).

    Parameters
    ----------
    run_dir : path
        Run folder (config.json, checkpoint.pt, log.jsonl).
    steps : int
        Total optimiser steps (resume continues up to this number).
    data : folder(s), ``"gen"``/``"gen:SEED[:POOL]"``, DataSource or list of sample dicts
        Training samples (``training.common.make_source``). Folders from ``dbh synth`` are much
        faster than rendering on the fly.
    val_data : same kinds, optional
        Validation samples (default: generator with seed :data:`DEFAULT_VAL_SEED`); the first
        ``n_val`` are used.
    size : {"tiny", "base"}
    batch_size, lr, weight_decay, warmup_steps, grad_clip
        AdamW, linear warm-up then cosine decay to 5 % of ``lr``; grad-norm clipping.
    aug : AugmentConfig, optional
        Default ``AugmentConfig()`` (colour/brightness/contrast jitter, blur, flip, crop).
    num_points : int, optional
        Point sampling for matching/loss (``None`` = full mask resolution).
    min_thing_area : int
        Tree instances smaller than this (pixels at a 256x256 input, scaled for other sizes)
        are not targets (see :func:`build_targets`).
    stop_at : int, optional
        Stop after this many total steps (time slice); continue later with ``resume=True``.
    init_weights : path, optional
        Warm start: a shipped ONNX file or a packed weights file of the same size; for size
        ``effl0`` (whose trunk always starts from its ImageNet weights) a shipped segmenter's
        ONNX file gives the head (:func:`~monodbh.models.training.pretrained.segmenter_head_from_onnx`).
    backbone_lr_scale : float
        The backbone's learning rate relative to ``lr`` (0.1 keeps a pretrained trunk near its
        ImageNet features, as Mask2Former fine-tunes its backbones).

    Returns
    -------
    dict
        ``{"step", "val"}`` (last validation metrics).
    """
    device = select_device(threads)
    spec = get_spec("segmenter", size)
    source = make_source(data, default_seed=seed, size=gen_size)
    val_source = (make_source(val_data, default_seed=DEFAULT_VAL_SEED, size=gen_size)
                  if val_data is not None else _default_source(DEFAULT_VAL_SEED, gen_size))
    aug = aug if aug is not None else AugmentConfig()
    torch.manual_seed(seed)
    model = build("segmenter", size).to(device)
    pretrained: dict[str, Any] = {}
    if model.cfg.backbone == "effl0" and not (resume and (Path(run_dir) / "checkpoint.pt").exists()):
        # ImageNet weights for the trunk; a shipped segmenter (--init ONNX) gives the head
        from monodbh.models.training.pretrained import (load_efficientnet_lite0,
                                                        segmenter_head_from_onnx)

        pretrained["backbone_tensors"] = load_efficientnet_lite0(model.backbone)
        if init_weights and str(init_weights).endswith(".onnx"):
            info = segmenter_head_from_onnx(model, init_weights)
            pretrained.update(head_from=str(init_weights), head_tensors=info["copied"])
            init_weights = None
        if verbose:
            print(f"EfficientNet-Lite0 trunk from ImageNet weights ({pretrained})", flush=True)
    groups: dict[tuple[bool, bool], list[torch.nn.Parameter]] = {}
    for n, p in model.named_parameters():
        no_wd = p.ndim <= 1 or "query" in n or "level_embed" in n
        groups.setdefault((no_wd, n.startswith("backbone.")), []).append(p)
    optim = torch.optim.AdamW([{"params": ps, "weight_decay": 0.0 if no_wd else weight_decay,
                                "lr": lr * (backbone_lr_scale if trunk else 1.0)}
                               for (no_wd, trunk), ps in sorted(groups.items())], lr=lr)

    def lr_lambda(step: int) -> float:
        if step < warmup_steps:
            return (step + 1) / warmup_steps
        t = (step - warmup_steps) / max(1, steps - warmup_steps)
        return 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(t, 1.0)))

    sched = torch.optim.lr_scheduler.LambdaLR(optim, lr_lambda)
    crit = SetCriterion(num_points=num_points)
    config = {"kind": "segmenter", "size": size, "seed": seed, "batch_size": batch_size,
              "lr": lr, "backbone_lr_scale": backbone_lr_scale, "weight_decay": weight_decay,
              "warmup_steps": warmup_steps,
              "grad_clip": grad_clip, "num_points": num_points, "min_area": min_area,
              "min_thing_area": min_thing_area,
              "aug": aug.to_dict() if aug else None, "n_val": n_val,
              "data": _cfg(source), "val_data": _cfg(val_source), "gen_size": list(gen_size),
              "loss": {"eos_coef": 0.1, "w_class": 2.0, "w_mask": 5.0, "w_dice": 5.0},
              "device": str(device), "spec": spec.to_dict()}
    if pretrained:
        config["pretrained"] = pretrained

    def step_fn(step: int) -> dict[str, float]:
        imgs, tgts = make_batch(source, step, batch_size, seed, spec, aug, min_area,
                                min_thing_area)
        imgs = imgs.to(device)
        tgts = [{k: v.to(device) for k, v in t.items()} for t in tgts]
        preds = model.forward_all(imgs)
        loss, parts = crit(preds, tgts)
        optim.zero_grad(set_to_none=True)
        loss.backward()
        if grad_clip:
            parts["grad_norm"] = float(torch.nn.utils.clip_grad_norm_(model.parameters(), grad_clip))
        optim.step()
        sched.step()
        return parts

    val_cache: list[dict[str, Any]] = []

    def validate() -> dict[str, float]:
        if not val_cache:
            n = n_val if val_source.n is None else min(n_val, val_source.n)
            val_cache.extend(val_source.get(i) for i in range(n))
        return evaluate_segmenter(torch_predictor(model, device), val_cache, spec)

    return train_loop(run_dir, init_weights=init_weights, config=config, model=model, optimizer=optim, steps=steps,
                      step_fn=step_fn, validate_fn=validate if n_val > 0 else None,
                      resume=resume, scheduler=sched, log_every=log_every, val_every=val_every,
                      ckpt_every=ckpt_every, stop_at=stop_at, verbose=verbose)


def _cfg(source: DataSource) -> dict[str, Any]:
    try:
        return source.config()
    except NotImplementedError:
        return {"type": type(source).__name__}


# --------------------------------------------------------------------------- export hooks


def _pick(data: DataSource | None, n: int, seed: int) -> list[dict[str, Any]]:
    src = data if data is not None else _default_source(DEFAULT_VAL_SEED + seed)
    if src.n is None:
        return [src.get(i) for i in range(n)]
    rng = np.random.default_rng(seed)
    idx = rng.permutation(src.n)[:n] if src.n >= n else rng.integers(0, src.n, n)
    return [src.get(int(i)) for i in idx]


@register_calibration("segmenter")
def calibration_inputs(n: int, seed: int, spec: ModelSpec, data: DataSource | None
                       ) -> list[dict[str, np.ndarray]]:
    """``n`` preprocessed ``{"image": (1, 3, S, S)}`` feeds from ``data`` (default generator)."""
    pre = asdict(spec.preprocess[0])
    shape = spec.input("image").shape
    return [{"image": preprocess_image(s["rgb"], pre, shape)} for s in _pick(data, n, seed)]


@register_eval("segmenter")
def eval_hook(predict: Callable, n: int, seed: int, spec: ModelSpec,
              data: DataSource | None) -> dict[str, float]:
    """Task metrics (``roped_iou``, PQ...) of ``predict`` on ``n`` samples of ``data``."""
    return evaluate_segmenter(predict, _pick(data, n, seed), spec)
