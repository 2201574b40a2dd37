"""Train the segmenter's trunk head on its frozen features, and attach it to the shipped segmenter.

The head (:class:`~monodbh.models.modeling.trunk_head.TrunkHead`) reads the segmenter's
``mask_features`` and tells a tree's trunk from its crown and limbs. The segmenter stays frozen:
its ``mask_features`` are computed once per training photo (whole, and with ``--views`` as
tile-like crops, since the runtime runs the head over tiles) by the shipped int8 file (the
tensor the runtime will feed the head), cached, and the head alone is trained on them against the
generator's ``stem`` label (``dbh synth`` writes it: stems and the rope on them, not branches or
foliage). Shipping writes the head as its own int8 file (``models/trunk_head_int8.onnx``) and
adds the segmenter's ``mask_features`` to its file's outputs (copied out only when asked for, so
a run without it costs the same); the file's other outputs are checked bit-identical on the
validation photos, so every measurement stays as it was (the error model, measured for those
outputs, is re-stamped with the new file's SHA-256).

A segmenter shipped later by ``dbh export`` exposes no features: train and ship a new head on its
features, since the head is tied to the features it was trained on.

Usage::

    python -m monodbh.models.training.trunk_head train --out runs/trunk --data data/trunk_train \\
        --data data/trunk_train_r --data data/trunk_port --data data/trunk_zoom --val data/trunk_val \\
        --steps 3000 --views 3
    python -m monodbh.models.training.trunk_head ship runs/trunk --val data/trunk_val
    python -m monodbh.models.training.trunk_head eval data/trunk_val12 --tiles 0.5

Training-only (imports torch and onnx); imported by nothing on the measuring path.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import time
import warnings
from pathlib import Path
from typing import Any, Sequence

import numpy as np

__all__ = ["FEATURE_TENSOR", "THRESHOLD", "feature_tensor_name", "FeatureExtractor", "jitter_photo", "tile_views", "fit_head",
           "load_features",
           "train", "evaluate", "expose_features", "export_head", "evaluate_onnx", "ship", "score_shipped", "main"]

#: the segmenter's mask-feature tensor (fp32 export; the int8 file reads it after its
#: DequantizeLinear)
FEATURE_TENSOR = "/pixel_decoder/mask_proj/Conv_output_0"
#: trunk where the head's probability is at least this (fixed before any real photo was scored;
#: the validation IoU is flat over 0.4-0.5, ``docs/decisions/trunk-head.md``)
THRESHOLD = 0.5
#: training photos' labels and features are kept at the segmenter's input side
LABEL_SIDE = 256


def _onnx():
    import onnx
    return onnx


def feature_tensor_name(model) -> str:
    """Name of the mask-feature tensor in a segmenter graph (``onnx.ModelProto``): the int8
    file's dequantized copy where there is one, else the fp32 tensor itself."""
    produced = {o for n in model.graph.node for o in n.output}
    for name in (FEATURE_TENSOR + "_DequantizeLinear_Output", FEATURE_TENSOR):
        if name in produced:
            return name
    raise ValueError(f"no mask-feature tensor {FEATURE_TENSOR!r} in this segmenter graph")


class FeatureExtractor:
    """The segmenter with its mask features exposed: photo -> ``(D, S/4, S/4)`` float32.

    Parameters
    ----------
    path : path, optional
        Segmenter ONNX file (default: the shipped one).
    threads : int
    """

    def __init__(self, path: str | os.PathLike | None = None, threads: int = 2) -> None:
        import onnxruntime as ort
        from onnx import TensorProto, helper

        from monodbh.models.runtime.common import session_options
        from monodbh.models.runtime.segmenter import Segmenter
        self.segmenter = Segmenter(path, threads=threads, trunk_head=None)
        model = _onnx().load(str(self.segmenter.path))
        self.name = feature_tensor_name(model)
        model.graph.output.append(helper.make_tensor_value_info(self.name, TensorProto.FLOAT, None))
        self.session = ort.InferenceSession(model.SerializeToString(), session_options(threads),
                                            providers=["CPUExecutionProvider"])
        self.sha256 = hashlib.sha256(self.segmenter.path.read_bytes()).hexdigest()

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        x = self.segmenter.preprocess(rgb, "image")
        return self.session.run([self.name], {"image": x})[0][0]


def _stem_label(stem: np.ndarray) -> np.ndarray:
    """(H, W) bool -> (LABEL_SIDE, LABEL_SIDE) uint8 share of trunk pixels x 255 (the photo
    stretched as the segmenter's input is)."""
    import cv2
    y = cv2.resize(stem.astype(np.float32), (LABEL_SIDE, LABEL_SIDE), interpolation=cv2.INTER_AREA)
    return np.round(y * 255).astype(np.uint8)


def jitter_photo(rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A photometric variant of ``rgb`` (H, W, 3) uint8: gamma 0.6-1.6, contrast 0.7-1.3,
    brightness -25..25, saturation 0.6-1.4, and a light blur on a third (the camera responses
    and exposures the generator's looks do not span)."""
    import cv2
    x = (rgb.astype(np.float32) / 255.0) ** rng.uniform(0.6, 1.6)
    grey = x.mean(axis=2, keepdims=True)
    x = grey + (x - grey) * rng.uniform(0.6, 1.4)
    x = (x - 0.5) * rng.uniform(0.7, 1.3) + 0.5 + rng.uniform(-0.1, 0.1)
    out = np.clip(x * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if rng.random() < 1 / 3:
        out = cv2.GaussianBlur(out, (0, 0), rng.uniform(0.5, 1.2))
    return out


def tile_views(rgb: np.ndarray, stem: np.ndarray, n: int, rng: np.random.Generator,
               frac: tuple[float, float] = (0.4, 0.75), tilt_deg: float = 0.0) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` square crops ``(rgb (s, s, 3), stem (s, s))`` of side ``frac`` x the photo's long side
    (at most its short side), at random places, each photometrically jittered
    (:func:`jitter_photo`) on half: the tiles that ``Segmenter.trunk_map`` feeds the head, where
    a trunk is twice as wide relative to the input as in the whole photo. ``tilt_deg``: half of
    the crops are turned about their centre by an angle drawn in +-``tilt_deg`` (the photo
    mirrored past its border), as a leaning stem or a tilted camera shows a trunk; 0 draws
    nothing more, so the crops are those of a run without it.

    Examples
    --------
    >>> rgb = np.zeros((60, 80, 3), np.uint8); stem = np.zeros((60, 80), bool); stem[:, 38:42] = True
    >>> views = tile_views(rgb, stem, 4, np.random.default_rng(0), tilt_deg=45)
    >>> [v[0].shape[:2] == v[1].shape for v in views]
    [True, True, True, True]
    """
    import cv2
    H, W = rgb.shape[:2]
    out = []
    for _ in range(n):
        s = int(round(min(rng.uniform(*frac) * max(H, W), min(H, W))))
        y0, x0 = int(rng.integers(0, H - s + 1)), int(rng.integers(0, W - s + 1))
        jitter = rng.random() < 0.5
        if tilt_deg and rng.random() < 0.5:
            rot = cv2.getRotationMatrix2D((x0 + (s - 1) / 2, y0 + (s - 1) / 2), rng.uniform(-tilt_deg, tilt_deg), 1.0)
            rot[:, 2] -= (x0, y0)
            crop = cv2.warpAffine(rgb, rot, (s, s), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
            label = cv2.warpAffine(stem.astype(np.uint8), rot, (s, s), flags=cv2.INTER_NEAREST,
                                   borderMode=cv2.BORDER_REFLECT_101).astype(bool)
        else:
            crop, label = np.ascontiguousarray(rgb[y0:y0 + s, x0:x0 + s]), stem[y0:y0 + s, x0:x0 + s]
        out.append((jitter_photo(crop, rng) if jitter else crop, label))
    return out


def load_features(folder: str | os.PathLike, extractor: FeatureExtractor,
                  cache_dir: str | os.PathLike, views: int = 0, seed: int = 0,
                  tilt_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Features ``(N (1 + views), D, h, w)`` float16 and labels ``(N (1 + views), 256, 256)``
    uint8 of a ``dbh synth`` folder's N photos, cached in ``cache_dir`` per folder, segmenter
    file and views: each whole photo, then its ``views`` tile-like crops (:func:`tile_views`,
    drawn from ``seed`` and the sample's index; half of them turned by up to ``tilt_deg``).

    Raises
    ------
    ValueError
        The folder's samples have no ``stem`` label (rendered before it existed).
    """
    from monodbh.models.synthetic.io import list_samples, read_sample
    folder = Path(folder)
    tag = (f"_v{views}s{seed}" + (f"t{tilt_deg:g}" if tilt_deg else "")) if views else ""
    cache = Path(cache_dir) / f"{folder.name}_{extractor.sha256[:12]}{tag}.npz"
    if cache.exists():
        with np.load(cache) as z:
            return z["F"], z["Y"]
    feats, labels = [], []
    for i in list_samples(folder):
        s = read_sample(folder, i)
        if "stem" not in s:
            raise ValueError(f"{folder}: sample {i:06d} has no 'stem' label; render it again with dbh synth")
        pairs = [(s["rgb"], s["stem"])]
        if views:
            pairs += tile_views(s["rgb"], s["stem"], views, np.random.default_rng([seed, i]), tilt_deg=tilt_deg)
        for rgb, stem in pairs:
            feats.append(extractor(rgb).astype(np.float16))
            labels.append(_stem_label(stem))
    if not feats:
        raise ValueError(f"{folder}: no samples")
    F, Y = np.stack(feats), np.stack(labels)
    cache.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_name(cache.stem + ".tmp.npz")
    np.savez(tmp, F=F, Y=Y)
    os.replace(tmp, cache)
    return F, Y


def _logits_at_labels(head, x):
    from torch.nn import functional as TF
    return TF.interpolate(head(x), size=(LABEL_SIDE, LABEL_SIDE), mode="bilinear", align_corners=False)


def _pixel_scores(masks, threshold: float) -> dict[str, float]:
    """Scores of ``(predicted, true)`` trunk masks (each (h, w) bool), one pair per photo:
    ``iou`` (all pixels pooled), ``iou_per_photo`` (mean), ``recall``, ``precision``."""
    counts = np.array([((P & G).sum(), (P | G).sum(), P.sum(), G.sum()) for P, G in masks], np.float64)
    inter, union, pred, true = counts.reshape(-1, 4).T
    return {"photos": int(len(counts)), "iou": float(inter.sum() / max(union.sum(), 1)),
            "iou_per_photo": float(np.mean(inter / np.maximum(union, 1))),
            "recall": float(inter.sum() / max(true.sum(), 1)),
            "precision": float(inter.sum() / max(pred.sum(), 1)), "threshold": threshold}


def evaluate(head, F: np.ndarray, Y: np.ndarray, threshold: float = THRESHOLD,
             batch: int = 16) -> dict[str, float]:
    """Pixel scores (:func:`_pixel_scores`) of the head on features ``F`` (N, D, h, w) against
    labels ``Y`` (N, 256, 256) uint8."""
    import torch
    head.eval()
    t = float(np.log(threshold / (1 - threshold)))

    def masks():
        with torch.no_grad():
            for a in range(0, len(F), batch):
                lo = _logits_at_labels(head, torch.from_numpy(F[a:a + batch].astype(np.float32)))[:, 0].numpy()
                yield from zip(lo > t, Y[a:a + batch] >= 128)
    return _pixel_scores(masks(), threshold)


def fit_head(head, draw, out: Path, config: dict[str, Any], steps: int, lr: float, seed: int, resume: bool,
             stop_at: int | None, checkpoint_every: int, log=print) -> bool:
    """The resumable training loop of a trunk head on cached features: AdamW with a one-cycle
    learning rate, BCE + soft Dice against the ``stem`` label at 256 x 256 (:data:`LABEL_SIDE`).
    ``draw(rng) -> (x, y)`` gives a batch (features for ``head``, labels ``(B, 1, 256, 256)`` in
    0-1) from the run's random generator. ``out/checkpoint.pt`` (every ``checkpoint_every``
    steps and at the end; ``resume`` goes on from it when its ``config`` is this one) and
    ``out/log.jsonl``; ``out/config.json`` holds ``config``. Returns whether all ``steps`` ran
    (False when stopped at ``stop_at``)."""
    import torch
    from torch.nn import functional as TF

    opt = torch.optim.AdamW(head.parameters(), lr=lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, lr, total_steps=steps, pct_start=0.05)
    rng = np.random.default_rng(seed)
    step = 0
    ck = out / "checkpoint.pt"
    if resume and ck.exists():
        state = torch.load(ck, weights_only=False)
        if state["config"] != config:
            raise ValueError(f"{ck}: another run's checkpoint (its config differs)")
        head.load_state_dict(state["head"]); opt.load_state_dict(state["opt"])
        sched.load_state_dict(state["sched"]); rng.bit_generator.state = state["rng"]
        step = state["step"]
    (out / "config.json").write_text(json.dumps(config, indent=1) + "\n")
    t0 = time.time()
    head.train()
    with open(out / "log.jsonl", "a") as logf:
        while step < min(steps, stop_at or steps):
            x, y = draw(rng)
            lo = _logits_at_labels(head, x)
            bce = TF.binary_cross_entropy_with_logits(lo, y)
            p = torch.sigmoid(lo)
            dice = 1 - (2 * (p * y).sum((1, 2, 3)) + 1) / (p.sum((1, 2, 3)) + y.sum((1, 2, 3)) + 1)
            loss = bce + dice.mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            step += 1
            if step % 50 == 0 or step == steps:
                logf.write(json.dumps({"step": step, "loss": float(loss.detach()), "bce": float(bce.detach()),
                                       "s": round(time.time() - t0, 1)}) + "\n")
                logf.flush()
            if step % checkpoint_every == 0 or step == steps:
                tmp = ck.with_suffix(".tmp")
                torch.save({"config": config, "head": head.state_dict(), "opt": opt.state_dict(),
                            "sched": sched.state_dict(), "rng": rng.bit_generator.state, "step": step}, tmp)
                os.replace(tmp, ck)
                log(f"{out}: step {step}/{steps}, loss {float(loss.detach()):.4f}")
    return step >= steps


def train(out: str | os.PathLike, data: Sequence[str | os.PathLike], val: Sequence[str | os.PathLike] = (),
          steps: int = 1500, batch: int = 16, lr: float = 2e-3, seed: int = 0,
          segmenter: str | os.PathLike | None = None, threads: int = 2,
          checkpoint_every: int = 250, resume: bool = False, stop_at: int | None = None,
          head_cfg=None, views: int = 0, tilt_deg: float = 0.0, log=print) -> dict[str, Any]:
    """Train a head on the segmenter's features of ``data`` (resumable from ``out/checkpoint.pt``).

    Writes ``out/config.json``, ``out/checkpoint.pt`` (every ``checkpoint_every`` steps and at the
    end), ``out/log.jsonl`` and ``out/head.pt`` (the final weights), and returns the validation
    scores of :func:`evaluate` per ``val`` folder (also in ``out/val.json``). ``stop_at``: stop,
    checkpointed, after this many steps (``{}`` returned; ``resume=True`` goes on).
    ``head_cfg``: a :class:`~monodbh.models.modeling.trunk_head.TrunkHeadConfig` (default the
    shipped size). ``views``: tile-like crops per training photo besides the whole photo
    (:func:`tile_views`; validation stays on whole photos); ``tilt_deg``: half of those crops
    turned by up to that angle.
    """
    import torch

    from monodbh.models.modeling.trunk_head import TrunkHead, TrunkHeadConfig
    head_cfg = head_cfg or TrunkHeadConfig()
    torch.set_num_threads(threads)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ext = FeatureExtractor(segmenter, threads)
    cache = out / "features"
    parts = [load_features(d, ext, cache, views, seed, tilt_deg) for d in data]
    F = np.concatenate([p[0] for p in parts])
    Y = np.concatenate([p[1] for p in parts])
    cfg = {"data": [str(d) for d in data], "val": [str(v) for v in val], "steps": steps, "batch": batch,
           "lr": lr, "seed": seed, "segmenter_sha256": ext.sha256, "photos": int(len(F)) // (1 + views), "views": views,
           "head": {"in_ch": head_cfg.in_ch, "ch": head_cfg.ch, "dilations": list(head_cfg.dilations)}}
    if tilt_deg:
        cfg["tilt_deg"] = tilt_deg
    torch.manual_seed(seed)
    head = TrunkHead(head_cfg)

    def draw(rng):
        idx = rng.integers(0, len(F), batch)
        x = torch.from_numpy(F[idx].astype(np.float32))
        y = torch.from_numpy(Y[idx].astype(np.float32) / 255.0)[:, None]
        if rng.random() < 0.5:                     # mirror: the features roughly mirror too
            x, y = x.flip(-1), y.flip(-1)
        return x, y
    if not fit_head(head, draw, out, cfg, steps, lr, seed, resume, stop_at, checkpoint_every, log):
        return {}
    torch.save(head.state_dict(), out / "head.pt")
    scores = {str(v): evaluate(head, *load_features(v, ext, cache)) for v in val}
    (out / "val.json").write_text(json.dumps(scores, indent=1) + "\n")
    return scores


def _load_head(run: Path):
    """The trained head of a run folder (its size from ``config.json``)."""
    import torch

    from monodbh.models.modeling.trunk_head import TrunkHead, TrunkHeadConfig
    h = json.loads((run / "config.json").read_text()).get("head", {})
    head = TrunkHead(TrunkHeadConfig(h.get("in_ch", 128), h.get("ch", 48), tuple(h.get("dilations", (1, 2, 4, 8)))))
    head.load_state_dict(torch.load(run / "head.pt"))
    return head.eval()


def expose_features(segmenter_path: str | os.PathLike, out_path: str | os.PathLike) -> None:
    """Write ``segmenter_path`` with its mask features as one more output, ``mask_features``
    ``(1, D, S/4, S/4)`` (an Identity of the tensor its mask queries read; listed in its spec)."""
    from monodbh.models.export.onnx_io import SPEC_METADATA_KEY
    from monodbh.models.runtime.segmenter import FEATURES_OUTPUT
    onnx = _onnx()
    seg = onnx.load(str(segmenter_path))
    spec = json.loads(next(p.value for p in seg.metadata_props if p.key == SPEC_METADATA_KEY))
    if any(o["name"] == FEATURES_OUTPUT for o in spec["outputs"]):
        raise ValueError(f"{segmenter_path}: already has a {FEATURES_OUTPUT} output")
    feat = feature_tensor_name(seg)
    S = int(spec["inputs"][0]["shape"][-1])
    inferred = onnx.shape_inference.infer_shapes(seg)
    vi = next(v for v in inferred.graph.value_info if v.name == feat)
    D = int(vi.type.tensor_type.shape.dim[1].dim_value)
    seg.graph.node.append(onnx.helper.make_node("Identity", [feat], [FEATURES_OUTPUT], name="mask_features_out"))
    shape = [1, D, S // 4, S // 4]
    seg.graph.output.append(onnx.helper.make_tensor_value_info(FEATURES_OUTPUT, onnx.TensorProto.FLOAT, shape))
    spec["outputs"].append({"name": FEATURES_OUTPUT, "shape": shape, "dtype": "float32",
                            "description": "per-pixel mask embedding at 1/4 input resolution (the trunk head's input)"})
    for p in seg.metadata_props:
        if p.key == SPEC_METADATA_KEY:
            p.value = json.dumps(spec, sort_keys=True)
    onnx.checker.check_model(seg)
    tmp = Path(str(out_path) + ".tmp")
    onnx.save(seg, str(tmp))
    os.replace(tmp, out_path)


def export_head(head, int8_path: str | os.PathLike, calibration: np.ndarray, info: dict[str, Any] | None = None,
                side: int | None = None) -> Path:
    """The head as its own int8 ONNX file (kind ``trunk_head``; static QDQ calibrated on the
    ``calibration`` features ``(N, D, h, w)``, the segmenter's recipe ``u8s8_qdq_all``; input
    side ``side``, default the features')."""
    side = int(side or calibration.shape[-1])
    import tempfile

    from monodbh.models.export.onnx_io import export_onnx
    from monodbh.models.export.quantize import quantize_int8, recipes_by_name
    from monodbh.models.modeling.trunk_head import trunk_head_spec
    spec = trunk_head_spec(head.cfg.in_ch, side, THRESHOLD, info)
    int8_path = Path(int8_path)
    with tempfile.TemporaryDirectory(dir=int8_path.parent) as td, warnings.catch_warnings():
        import torch
        warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)
        warnings.filterwarnings("ignore", category=DeprecationWarning)
        fp32 = Path(td) / "trunk_head_fp32.onnx"
        export_onnx(head.eval(), spec, fp32)
        feeds = [{"mask_features": np.asarray(f[None], np.float32)} for f in calibration]
        tmp = Path(td) / "trunk_head_int8.onnx"
        quantize_int8(fp32, tmp, feeds, spec, recipes_by_name(["u8s8_qdq_all"])[0])
        os.replace(tmp, int8_path)
    return int8_path


def evaluate_onnx(path: str | os.PathLike, F: np.ndarray, Y: np.ndarray,
                  threshold: float = THRESHOLD) -> dict[str, float]:
    """:func:`evaluate` of a trunk-head ONNX file (as the runtime runs it)."""
    from monodbh.models.runtime.segmenter import trunk_probability
    from monodbh.models.runtime.trunk_head import TrunkHead
    head = TrunkHead(path)
    side = (LABEL_SIDE, LABEL_SIDE)
    return _pixel_scores(((trunk_probability(head.logits(np.asarray(f[None], np.float32)), side) >= threshold,
                           y >= 128) for f, y in zip(F, Y)), threshold)


def _same_outputs(old: str | os.PathLike, new: str | os.PathLike, photos: Sequence[np.ndarray]) -> bool:
    """Whether the two segmenter files give bit-identical class and mask logits on ``photos``."""
    from monodbh.models.runtime.segmenter import Segmenter
    a, b = Segmenter(old, trunk_head=None), Segmenter(new, trunk_head=None)
    for rgb in photos:
        ra, rb = a.raw(rgb), b.raw(rgb)
        if not all(np.array_equal(x, y) for x, y in zip(ra, rb)):
            return False
    return True


def ship(run: str | os.PathLike, val: Sequence[str | os.PathLike], models_dir: str | os.PathLike | None = None,
         n_check: int = 16, n_calib: int = 32) -> dict[str, Any]:
    """Ship ``run``'s head as ``models_dir/trunk_head_int8.onnx`` and expose the segmenter's
    mask features; update ``models_dir/manifest.json``.

    The run must have been trained on the features of the segmenter shipped now (or of the file
    it was before its features were exposed). The segmenter file is replaced only when its class
    and mask logits are bit-identical to the old one's on the first ``n_check`` photos of each
    ``val`` folder; its manifest entry gets the new SHA-256 and outputs, and the error model
    (measured for those outputs) the new SHA-256 where it held the old one. The head is
    quantised on ``n_calib`` training photos' features and scored on the ``val`` folders.
    """
    from monodbh.models.runtime.common import MODELS_DIR, load_manifest
    from monodbh.models.runtime.segmenter import FEATURES_OUTPUT, Segmenter
    from monodbh.models.synthetic.io import list_samples, read_sample
    from monodbh.models.training.common import atomic_write_text
    run = Path(run)
    models_dir = Path(models_dir or MODELS_DIR)
    man_path = models_dir / "manifest.json"
    manifest = load_manifest(man_path)
    entry = manifest["models"]["segmenter"]
    seg_path = models_dir / entry["file"]
    old_sha = hashlib.sha256(seg_path.read_bytes()).hexdigest()
    cfg = json.loads((run / "config.json").read_text())
    if cfg["segmenter_sha256"] not in (old_sha, entry.get("features_of")):
        raise ValueError(f"{run}: trained on another segmenter's features ({cfg['segmenter_sha256'][:12]}, "
                         f"shipped {old_sha[:12]})")
    head = _load_head(run)
    restamped = False
    if FEATURES_OUTPUT not in Segmenter(seg_path, trunk_head=None).output_names:
        new = seg_path.with_name(seg_path.stem + ".features.onnx")
        expose_features(seg_path, new)
        photos = [read_sample(v, i, arrays=False)["rgb"] for v in val for i in list_samples(v)[:n_check]]
        if not photos or not _same_outputs(seg_path, new, photos):
            new.unlink()
            raise ValueError(f"{new}: the segmenter's class and mask outputs changed (or no photo to check): not shipped")
        os.replace(new, seg_path)
        new_sha = hashlib.sha256(seg_path.read_bytes()).hexdigest()
        spec = Segmenter(seg_path, trunk_head=None).spec
        entry["sha256"] = new_sha
        entry["features_of"] = old_sha
        entry["outputs"] = [{k: o[k] for k in ("dtype", "name", "shape")} for o in spec["outputs"]]
        if "spec" in entry:
            entry["spec"] = spec
        em = manifest.get("error_model") or {}
        restamped = (em.get("models") or {}).get("segmenter") == old_sha
        if restamped:
            em["models"]["segmenter"] = new_sha
    ext = FeatureExtractor(seg_path)
    cache = run / "features"
    calib = load_features(cfg["data"][0], ext, cache, cfg.get("views", 0), cfg.get("seed", 0),
                          cfg.get("tilt_deg", 0.0))[0][:n_calib]
    info = {"data": [Path(d).name for d in cfg["data"]], "steps": cfg["steps"], "photos": cfg["photos"],
            "views": cfg.get("views", 0)}
    if cfg.get("tilt_deg"):
        info["tilt_deg"] = cfg["tilt_deg"]
    out = models_dir / "trunk_head_int8.onnx"
    export_head(head, out, calib, info)
    scores = {Path(v).name: {k: (round(x, 4) if isinstance(x, float) else x) for k, x in
                             evaluate_onnx(out, *load_features(v, ext, cache)).items()} for v in val}
    from monodbh.models.runtime.trunk_head import TrunkHead
    th = TrunkHead(out)
    manifest["models"]["trunk_head"] = {
        "file": out.name, "sha256": hashlib.sha256(out.read_bytes()).hexdigest(), "spec": th.spec,
        "inputs": [{k: o[k] for k in ("dtype", "name", "shape")} for o in th.spec["inputs"]],
        "outputs": [{k: o[k] for k in ("dtype", "name", "shape")} for o in th.spec["outputs"]],
        "precision": "int8", "quant_recipe": "u8s8_qdq_all", "training": info, "validation": {"int8": scores},
        "exported_at": time.strftime("%Y-%m-%dT%H:%M:%S+00:00", time.gmtime())}
    atomic_write_text(man_path, json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    return {"segmenter": str(seg_path), "segmenter_sha256": entry["sha256"], "error_model_restamped": restamped,
            "trunk_head": str(out), "validation": scores}


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m monodbh.models.training.trunk_head",
                                 description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="train a head on the shipped segmenter's features")
    t.add_argument("--out", required=True, type=Path)
    t.add_argument("--data", required=True, action="append", type=Path, help="dbh synth folder (repeatable)")
    t.add_argument("--val", action="append", type=Path, default=[], help="validation folder (repeatable)")
    t.add_argument("--steps", type=int, default=1500)
    t.add_argument("--batch", type=int, default=16)
    t.add_argument("--lr", type=float, default=2e-3)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--threads", type=int, default=2)
    t.add_argument("--views", type=int, default=0,
                   help="tile-like crops per training photo besides the whole photo (default 0)")
    t.add_argument("--tilt", type=float, default=0.0, metavar="DEG",
                   help="turn half of the crops by an angle within +-DEG (default 0: upright)")
    t.add_argument("--resume", action="store_true")
    s = sub.add_parser("ship", help="attach a trained head to the shipped segmenter")
    s.add_argument("run", type=Path)
    s.add_argument("--val", required=True, action="append", type=Path,
                   help="folder whose photos check the segmenter's other outputs unchanged")
    e = sub.add_parser("eval", help="score a run's head (or the shipped one) on dbh synth folders")
    e.add_argument("folders", nargs="+", type=Path)
    e.add_argument("--run", type=Path, help="default: the head attached to the shipped segmenter")
    e.add_argument("--tiles", type=float, metavar="F",
                   help="the shipped head's trunk map over tiles of side F x the photo's long side "
                        "(Segmenter.trunk_map, dbh reconstruct's: 0.5), scored at the photo's resolution")
    e.add_argument("--threshold", type=float, metavar="P",
                   help="score the run's or the shipped head's map from this probability on (default 0.5)")
    a = ap.parse_args(argv)
    if a.cmd == "eval" and a.threshold is not None and not 0 < a.threshold < 1:
        ap.error(f"--threshold must be a probability in (0, 1), got {a.threshold}")
    if a.cmd == "train":
        scores = train(a.out, a.data, a.val, a.steps, a.batch, a.lr, a.seed, threads=a.threads, resume=a.resume,
                       views=a.views, tilt_deg=a.tilt)
        print(json.dumps(scores, indent=1))
    elif a.cmd == "ship":
        print(json.dumps(ship(a.run, a.val), indent=1))
    else:
        print(json.dumps(_eval_cmd(a.folders, a.run, a.tiles, a.threshold), indent=1))
    return 0


def score_shipped(folder: str | os.PathLike, n: int | None = None,
                  models_dir: str | os.PathLike | None = None, tiles: float | None = None,
                  threshold: float | None = None) -> dict[str, Any]:
    """The shipped trunk head (as the runtime runs it: int8, on the segmenter's ``mask_features``)
    on the first ``n`` samples of a ``dbh synth`` folder: :func:`evaluate`'s scores, or ``{}``
    where the folder was rendered without the ``stem`` label. With ``tiles``, the trunk map
    ``Segmenter.trunk_map(rgb, tile_frac=tiles)`` (``dbh reconstruct``'s) against the label at the
    photo's own resolution instead of one pass at the segmenter's input side. ``threshold``: trunk
    pixels from this probability on (default the head's own)."""
    from monodbh.models.runtime.common import MODELS_DIR, load_manifest
    from monodbh.models.runtime.segmenter import Segmenter, trunk_probability
    from monodbh.models.synthetic.io import list_samples, read_sample
    mdir = Path(models_dir or MODELS_DIR)
    models = load_manifest(mdir / "manifest.json")["models"]
    seg = Segmenter(mdir / models["segmenter"]["file"], trunk_head=mdir / models["trunk_head"]["file"])
    th = seg.trunk_threshold if threshold is None else threshold
    idx = list_samples(folder)[:n]
    if not idx or "stem" not in read_sample(folder, idx[0]):
        return {}
    def masks():
        for i in idx:
            s = read_sample(folder, i)
            if tiles:
                yield seg.trunk_map(s["rgb"], None, tiles) >= th, s["stem"].astype(bool)
                continue
            tl = seg.raw_with_trunk(s["rgb"])[2]
            yield (trunk_probability(tl, (LABEL_SIDE, LABEL_SIDE)) >= th,
                   _stem_label(s["stem"]) >= 128)
    return {**_pixel_scores(masks(), th), **({"tiles": tiles} if tiles else {})}


def _eval_cmd(folders: Sequence[Path], run: Path | None, tiles: float | None = None,
              threshold: float | None = None) -> dict[str, Any]:
    """Scores of a run's head (on the shipped segmenter's features) or of the shipped head (in
    ``tiles`` where given), at ``threshold`` (default the head's)."""
    if run is not None and tiles:
        raise ValueError("--tiles scores the shipped head only: ship the run first, or leave --tiles out")
    if run is not None:
        ext = FeatureExtractor()
        head = _load_head(run)
        t = THRESHOLD if threshold is None else threshold
        return {str(f): evaluate(head, *load_features(f, ext, run / "features"), threshold=t) for f in folders}
    out = {}
    for f in folders:
        out[str(f)] = score_shipped(f, tiles=tiles, threshold=threshold)
        if not out[str(f)]:
            raise ValueError(f"{f}: no samples with a 'stem' label; render it again with dbh synth")
    return out


if __name__ == "__main__":
    raise SystemExit(main())
