"""Train and score the trunk network (training-only): a trunk decoder on frozen ImageNet features.

The segmenter's trunk head (:mod:`.trunk_head`) reads features the segmenter learnt on synthetic
scenes only, and on the real photos it reads 0.57-0.60 in tiles whatever its training data
(``docs/decisions/trunk-head.md``). :class:`~monodbh.models.modeling.trunk_net.TrunkNet` reads
EfficientNet-Lite0's ImageNet features instead (the ``pretrained`` extra's weights, kept frozen)
and trains only its decoder on the generator's ``stem`` label, on the same photos and tile-like
crops as the trunk head (:func:`.trunk_head.tile_views`). The backbone's four feature maps are
computed once per photo and view and cached per folder in the run folder.

``ship`` exports a run's network int8 into ``models/`` (``dbh reconstruct`` then reads its
trunk map). ``eval`` scores the shipped file (or ``--run``'s network in float32, or ``--onnx``'s
file): the trunk map in tiles (:func:`trunk_map`, blended as
``Segmenter.trunk_map``) on ``dbh synth`` folders at the photo's resolution, and the real
photos' hand-drawn trunk outlines (``real_trunk_bench``'s scores).

Usage::

    pip install -c constraints.txt -e ".[pretrained]"
    python -m monodbh.models.training.trunk_net train --out runs/trunk_net --data data/trunk_train \\
        --data data/trunk_train_r --data data/trunk_port --data data/trunk_zoom \\
        --val data/trunk_val --val data/trunk_val_h --steps 3000 --views 3
    python -m monodbh.models.training.trunk_net eval data/trunk_val12 data/trunk_val12_h --run runs/trunk_net \\
        --tiles 0.5 --real ../shared/data/real_trees
    python -m monodbh.models.training.trunk_net ship runs/trunk_net --calib data/trunk_train \\
        --val data/trunk_val12 --val data/trunk_val12_h
    python -m monodbh.models.training.trunk_net eval data/bench data/bench_heldout --tiles 0.5   # the shipped int8 file

Imported by nothing (a command); imports the modeling, the synthetic data's reader and the
trunk head's training helpers.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from monodbh.models.training.trunk_head import (LABEL_SIDE, THRESHOLD, _logits_at_labels, _pixel_scores, _stem_label, fit_head,
                                                tile_views)

__all__ = ["INPUT_SIDE", "LABEL_SIDE", "photo_input", "load_backbone", "load_features", "train", "load_net", "export", "ship",
           "OnnxTrunkNet", "trunk_map", "score_folder", "score_real", "main"]

#: the network's input side (the photo or tile stretched to it, as the segmenter's)
INPUT_SIDE = 256
_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
_STD = np.array([0.229, 0.224, 0.225], np.float32)


def photo_input(rgb: np.ndarray, side: int = INPUT_SIDE) -> np.ndarray:
    """``(H, W, 3)`` uint8 -> ``(3, side, side)`` float32, stretched (area) and ImageNet-normalised.

    Examples
    --------
    >>> photo_input(np.zeros((30, 50, 3), np.uint8), 32).shape
    (3, 32, 32)
    """
    import cv2
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) photo, got shape {rgb.shape}")
    x = cv2.resize(rgb, (side, side), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
    return ((x - _MEAN) / _STD).transpose(2, 0, 1)


def load_backbone(pretrained: bool = True):
    """EfficientNet-Lite0's trunk in eval mode, frozen; with ``pretrained`` its ImageNet weights
    (:func:`.pretrained.load_efficientnet_lite0`; RuntimeError without the ``pretrained`` extra),
    else random weights (tests)."""
    from monodbh.models.modeling.efficientnet_lite import EfficientNetLite0
    net = EfficientNetLite0()
    if pretrained:
        from monodbh.models.training.pretrained import load_efficientnet_lite0
        load_efficientnet_lite0(net)
    net.eval()
    for p in net.parameters():
        p.requires_grad_(False)
    return net


def _features(backbone, photos: Sequence[np.ndarray]) -> list[np.ndarray]:
    import torch
    with torch.no_grad():
        x = torch.from_numpy(np.stack([photo_input(r) for r in photos]))
        return [f.numpy().astype(np.float16) for f in backbone(x)]


def load_features(folder: str | os.PathLike, backbone, cache_dir: str | os.PathLike, views: int = 0,
                  seed: int = 0, batch: int = 32) -> tuple[list[np.ndarray], np.ndarray]:
    """The backbone's four feature maps ``[(N (1 + views), C_i, s_i, s_i)]`` float16 and labels
    ``(N (1 + views), 256, 256)`` uint8 of a ``dbh synth`` folder: each photo whole, then its
    ``views`` tile-like crops (:func:`.trunk_head.tile_views` from ``seed`` and the sample's
    index), cached as ``cache_dir/<folder>_v<views>s<seed>.npz``.

    Raises
    ------
    ValueError
        No samples, or a sample without the ``stem`` label.
    """
    from monodbh.models.synthetic.io import list_samples, read_sample
    folder = Path(folder)
    cache = Path(cache_dir) / f"{folder.name}_v{views}s{seed}.npz"
    if cache.exists():
        with np.load(cache) as z:
            return [z[f"f{i}"] for i in range(4)], z["Y"]
    feats: list[list[np.ndarray]] = [[], [], [], []]
    labels: list[np.ndarray] = []
    pending: list[tuple[np.ndarray, np.ndarray]] = []

    def flush():
        for i, f in enumerate(_features(backbone, [r for r, _ in pending])):
            feats[i].append(f)
        labels.extend(_stem_label(s) for _, s in pending)
        pending.clear()
    for i in list_samples(folder):
        s = read_sample(folder, i)
        if "stem" not in s:
            raise ValueError(f"{folder}: sample {i:06d} has no 'stem' label; render it again with dbh synth")
        pending.append((s["rgb"], s["stem"]))
        if views:
            pending.extend(tile_views(s["rgb"], s["stem"], views, np.random.default_rng([seed, i])))
        if len(pending) >= batch:
            flush()
    if pending:
        flush()
    if not labels:
        raise ValueError(f"{folder}: no samples")
    F = [np.concatenate(f) for f in feats]
    Y = np.stack(labels)
    cache.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_name(cache.stem + ".tmp.npz")
    np.savez(tmp, **{f"f{i}": f for i, f in enumerate(F)}, Y=Y)
    os.replace(tmp, cache)
    return F, Y


def _evaluate(head, F: list[np.ndarray], Y: np.ndarray, batch: int = 32) -> dict[str, float]:
    import torch
    head.eval()

    def masks():
        for a in range(0, len(Y), batch):
            with torch.no_grad():
                lo = _logits_at_labels(head, [torch.from_numpy(f[a:a + batch].astype(np.float32)) for f in F])
            for p, y in zip(lo[:, 0].numpy(), Y[a:a + batch]):
                yield p >= 0.0, y >= 128
    out = _pixel_scores(masks(), THRESHOLD)
    head.train()
    return out


def train(out: str | os.PathLike, data: Sequence[str | os.PathLike], val: Sequence[str | os.PathLike] = (),
          steps: int = 3000, batch: int = 16, lr: float = 2e-3, seed: int = 0, threads: int = 2,
          checkpoint_every: int = 250, resume: bool = False, stop_at: int | None = None, views: int = 3,
          cfg=None, pretrained: bool = True, log=print) -> dict[str, Any]:
    """Train the decoder on the frozen backbone's features of ``data`` (resumable from
    ``out/checkpoint.pt``); the same schedule and loss as the trunk head (AdamW, one-cycle, BCE +
    soft Dice against the ``stem`` label at 256 x 256, half the batches mirrored).

    Writes ``out/config.json``, ``out/checkpoint.pt``, ``out/log.jsonl``, ``out/head.pt`` and
    ``out/val.json`` (one-pass scores per ``val`` folder, returned; ``{}`` when stopped at
    ``stop_at``). ``cfg``: a :class:`~monodbh.models.modeling.trunk_net.TrunkNetConfig`.
    """
    import torch

    from monodbh.models.modeling.trunk_net import TrunkNetConfig, TrunkNetHead
    cfg = cfg or TrunkNetConfig()
    torch.set_num_threads(threads)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    backbone = load_backbone(pretrained)
    cache = out / "features"
    parts = [load_features(d, backbone, cache, views, seed) for d in data]
    F = [np.concatenate([p[0][i] for p in parts]) for i in range(4)]
    Y = np.concatenate([p[1] for p in parts])
    conf = {"data": [str(d) for d in data], "val": [str(v) for v in val], "steps": steps, "batch": batch,
            "lr": lr, "seed": seed, "views": views, "pretrained": pretrained, "photos": int(len(Y)) // (1 + views),
            "head": {"lat": cfg.lat, "ch": cfg.ch, "dilations": list(cfg.dilations)}}
    torch.manual_seed(seed)
    head = TrunkNetHead(cfg)

    def draw(rng):
        idx = np.sort(rng.integers(0, len(Y), batch))
        xs = [torch.from_numpy(f[idx].astype(np.float32)) for f in F]
        y = torch.from_numpy(Y[idx].astype(np.float32) / 255.0)[:, None]
        if rng.random() < 0.5:
            xs, y = [x.flip(-1) for x in xs], y.flip(-1)
        return xs, y
    if not fit_head(head, draw, out, conf, steps, lr, seed, resume, stop_at, checkpoint_every, log):
        return {}
    torch.save(head.state_dict(), out / "head.pt")
    scores = {str(v): _evaluate(head, *load_features(v, backbone, cache)) for v in val}
    (out / "val.json").write_text(json.dumps(scores, indent=1) + "\n")
    return scores


def load_net(run: str | os.PathLike):
    """The run's :class:`~monodbh.models.modeling.trunk_net.TrunkNet` (its backbone's weights as
    trained on, its decoder from ``head.pt``), in eval mode."""
    import torch

    from monodbh.models.modeling.trunk_net import TrunkNet, TrunkNetConfig
    run = Path(run)
    conf = json.loads((run / "config.json").read_text())
    h = conf["head"]
    net = TrunkNet(TrunkNetConfig(h["lat"], h["ch"], tuple(h["dilations"])))
    net.backbone = load_backbone(conf.get("pretrained", True))
    net.head.load_state_dict(torch.load(run / "head.pt"))
    return net.eval()


def export(run: str | os.PathLike, int8_path: str | os.PathLike, calibration: str | os.PathLike,
           n_calib: int = 32, recipe: str = "u8s8_qdq_all") -> Path:
    """The run's network as one int8 ONNX file (kind ``trunk_net``: image in, trunk logits out;
    static QDQ with ``recipe``, calibrated on the first ``n_calib`` photos of the ``dbh synth``
    folder ``calibration``, half of them whole and half as tile-like crops)."""
    import tempfile
    import warnings

    from monodbh.models.export.onnx_io import export_onnx
    from monodbh.models.export.quantize import quantize_int8, recipes_by_name
    from monodbh.models.modeling.trunk_net import trunk_net_spec
    from monodbh.models.synthetic.io import list_samples, read_sample
    run, int8_path = Path(run), Path(int8_path)
    conf = json.loads((run / "config.json").read_text())
    info = {k: conf[k] for k in ("data", "steps", "photos", "views")}
    spec = trunk_net_spec(INPUT_SIDE, THRESHOLD, info)
    feeds = []
    for k, i in enumerate(list_samples(calibration)[:n_calib]):
        s = read_sample(calibration, i)
        rgb = s["rgb"] if k % 2 == 0 else tile_views(s["rgb"], s["stem"], 1, np.random.default_rng([7, i]))[0][0]
        feeds.append({"image": photo_input(rgb)[None]})
    if not feeds:
        raise ValueError(f"{calibration}: no samples to calibrate on")
    int8_path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=int8_path.parent) as td, warnings.catch_warnings():
        import torch
        warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)
        warnings.filterwarnings("ignore", category=DeprecationWarning)
        fp32 = Path(td) / "trunk_net_fp32.onnx"
        export_onnx(load_net(run), spec, fp32)
        tmp = Path(td) / "trunk_net_int8.onnx"
        quantize_int8(fp32, tmp, feeds, spec, recipes_by_name([recipe])[0])
        os.replace(tmp, int8_path)
    return int8_path


def ship(run: str | os.PathLike, calibration: str | os.PathLike, val: Sequence[str | os.PathLike] = (),
         models_dir: str | os.PathLike | None = None, n_calib: int = 32, tiles: float = 0.5) -> dict[str, Any]:
    """Ship ``run``'s network as ``models_dir/trunk_net_int8.onnx`` (:func:`export`) and list it
    in ``models_dir/manifest.json`` (kind ``trunk_net``), with its int8 scores in ``tiles`` on
    the ``val`` folders as the runtime runs it. ``dbh reconstruct`` then reads its trunk map
    instead of the segmenter's trunk head's; no measurement reads either."""
    import hashlib

    from monodbh.models.runtime.common import MODELS_DIR, load_manifest
    from monodbh.models.runtime.trunk_net import TrunkNet
    from monodbh.models.training.common import atomic_write_text
    models_dir = Path(models_dir or MODELS_DIR)
    man_path = models_dir / "manifest.json"
    manifest = load_manifest(man_path)
    out = models_dir / "trunk_net_int8.onnx"
    tmp = models_dir / "trunk_net_int8.new.onnx"
    export(run, tmp, calibration, n_calib)
    os.replace(tmp, out)
    net = TrunkNet(out)
    scores = {Path(v).name: {k: (round(x, 4) if isinstance(x, float) else x) for k, x in
                             score_folder(net, v, tiles).items()} for v in val}
    conf = json.loads((Path(run) / "config.json").read_text())
    manifest["models"]["trunk_net"] = {
        "file": out.name, "sha256": hashlib.sha256(out.read_bytes()).hexdigest(), "spec": net.spec,
        "inputs": [{k: o[k] for k in ("dtype", "name", "shape")} for o in net.spec["inputs"]],
        "outputs": [{k: o[k] for k in ("dtype", "name", "shape")} for o in net.spec["outputs"]],
        "precision": "int8", "quant_recipe": "u8s8_qdq_all",
        "training": {k: conf[k] for k in ("data", "steps", "photos", "views")},
        "validation": {"int8": scores},
        "exported_at": time.strftime("%Y-%m-%dT%H:%M:%S+00:00", time.gmtime())}
    atomic_write_text(man_path, json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    return {"trunk_net": str(out), "bytes": out.stat().st_size, "validation": scores}


class OnnxTrunkNet:
    """An exported trunk network run by onnxruntime, called as the torch module is
    (``(B, 3, S, S)`` tensor -> ``(B, 1, S / 4, S / 4)`` tensor) so that :func:`trunk_map` and
    the scorers take either; ``seconds`` and ``passes`` count the time spent in it."""

    def __init__(self, path: str | os.PathLike, threads: int = 2) -> None:
        import onnxruntime as ort
        so = ort.SessionOptions()
        so.intra_op_num_threads = threads
        self.session = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
        self.seconds, self.passes = 0.0, 0

    def __call__(self, x):
        import torch
        t = time.perf_counter()
        out = [self.session.run(["trunk_logits"], {"image": np.ascontiguousarray(b[None], np.float32)})[0]
               for b in x.numpy()]
        self.seconds += time.perf_counter() - t
        self.passes += len(out)
        return torch.from_numpy(np.concatenate(out))


def trunk_map(net, rgb: np.ndarray, size: tuple[int, int] | None = None,
              tile_frac: float | None = 0.5) -> np.ndarray:
    """Trunk probability ``(H, W)`` float32 of a photo ``(H, W, 3)`` at ``size`` = (W, H) (default
    the photo's): over square tiles of ``tile_frac`` x its long side, half a tile apart, blended
    as ``Segmenter.trunk_map`` blends them (``tile_boxes``, ``tile_weight``); None: one pass."""
    import cv2
    import torch

    from monodbh.models.runtime.segmenter import tile_boxes, tile_weight, trunk_probability
    H, W = rgb.shape[:2]
    boxes = [(0, H, 0, W)] if tile_frac is None else tile_boxes(H, W, tile_frac)
    with torch.no_grad():
        logits = net(torch.from_numpy(np.stack([photo_input(np.ascontiguousarray(rgb[y0:y1, x0:x1]))
                                                 for y0, y1, x0, x1 in boxes])))[:, 0].numpy()
    total = np.zeros((H, W), np.float32)
    cover = np.zeros((H, W), np.float32)
    for box, lg in zip(boxes, logits):
        y0, y1, x0, x1 = box
        w = tile_weight(box, H, W) if tile_frac is not None else 1.0
        total[y0:y1, x0:x1] += w * trunk_probability(lg, (x1 - x0, y1 - y0))
        cover[y0:y1, x0:x1] += w
    prob = total / cover
    size = size or (W, H)
    if tuple(size) != (W, H):
        prob = cv2.resize(prob, (int(size[0]), int(size[1])), interpolation=cv2.INTER_LINEAR)
    return prob


def _map(net, rgb: np.ndarray, size, tiles) -> np.ndarray:
    """The trunk map of a torch-like network (:func:`trunk_map`) or of the runtime's
    :class:`~monodbh.models.runtime.trunk_net.TrunkNet` (its own ``trunk_map``)."""
    if hasattr(net, "trunk_map"):
        return net.trunk_map(rgb, size, tiles)
    return trunk_map(net, rgb, size, tiles)


def score_folder(net, folder: str | os.PathLike, tiles: float | None = 0.5, n: int | None = None) -> dict[str, Any]:
    """The trunk map (:func:`_map`) against the ``stem`` label of a ``dbh synth`` folder's first
    ``n`` photos (default all) at the photo's resolution (the trunk head's ``trunk_head eval
    --tiles``).

    Raises
    ------
    ValueError
        A sample without the ``stem`` label.
    """
    from monodbh.models.synthetic.io import list_samples, read_sample

    def masks():
        for i in list_samples(folder)[:n]:
            s = read_sample(folder, i)
            if "stem" not in s:
                raise ValueError(f"{folder}: sample {i:06d} has no 'stem' label; render it again with dbh synth")
            yield _map(net, s["rgb"], None, tiles) >= THRESHOLD, s["stem"].astype(bool)
    return {**_pixel_scores(masks(), THRESHOLD), "tiles": tiles}


class _BenchSegmenter:
    """What ``real_trunk_bench.score_photo`` asks of a segmenter, with the trunk map from the
    trunk network (the shipped segmenter gives the rest of the segmentation it draws)."""

    def __init__(self, net) -> None:
        from monodbh.models.runtime.segmenter import Segmenter
        self.net, self.seg, self.trunk_threshold = net, Segmenter(trunk_head=None), THRESHOLD

    def predict(self, rgb, size=None, trunk=False):
        r = self.seg.predict(rgb, size=size)
        if trunk:
            r.trunk_prob = _map(self.net, rgb, size, None)
        return r

    def trunk_map(self, rgb, size=None, tile_frac=0.5):
        return _map(self.net, rgb, size, tile_frac)


def score_real(net, folder: str | os.PathLike, tiles: float | None = 0.5,
               draw: Optional[Path] = None) -> tuple[dict, list[dict]]:
    """``real_trunk_bench --trunk [--tiles]`` with the trunk network's map: the summary and the
    per-trunk rows."""
    from monodbh.toolkit.evaluation import real_trunk_bench as rtb
    rows = rtb.run(Path(folder), rtb.load_outlines(), draw, segmenter=_BenchSegmenter(net), tiles=tiles, trunk=True)
    return rtb.summarise(rows), rows


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m monodbh.models.training.trunk_net",
                                 description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="train the decoder on the frozen ImageNet backbone's features")
    t.add_argument("--out", required=True, type=Path)
    t.add_argument("--data", required=True, action="append", type=Path, help="dbh synth folder (repeatable)")
    t.add_argument("--val", action="append", type=Path, default=[], help="validation folder (repeatable)")
    t.add_argument("--steps", type=int, default=3000)
    t.add_argument("--batch", type=int, default=16)
    t.add_argument("--lr", type=float, default=2e-3)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--threads", type=int, default=2)
    t.add_argument("--views", type=int, default=3, help="tile-like crops per photo besides the whole (default 3)")
    t.add_argument("--resume", action="store_true")
    e = sub.add_parser("eval", help="score the shipped network (or a run's, float32) on dbh synth folders "
                                    "and the real outlines")
    e.add_argument("folders", nargs="*", type=Path)
    e.add_argument("--run", type=Path, help="a run folder's network in float32 (default: the shipped int8 file)")
    e.add_argument("--tiles", type=float, metavar="F", help="tiles of side F x the long side (default: one pass)")
    e.add_argument("--real", type=Path, metavar="DIR", help="also the real photos' outlines (../shared/data/real_trees)")
    e.add_argument("--draw", type=Path, metavar="DIR", help="with --real: each photo's outlines and trunks")
    e.add_argument("--onnx", type=Path, metavar="FILE", help="an exported file other than the shipped one")
    sh = sub.add_parser("ship", help="export a run's network int8 into models/ and list it in the manifest")
    sh.add_argument("run", type=Path)
    sh.add_argument("--calib", required=True, type=Path, help="dbh synth folder to calibrate on")
    sh.add_argument("--val", action="append", type=Path, default=[], help="folder scored in tiles (repeatable)")
    x = sub.add_parser("export", help="write a run's network as an int8 ONNX file (not shipped)")
    x.add_argument("run", type=Path)
    x.add_argument("out", type=Path)
    x.add_argument("--calib", required=True, type=Path, help="dbh synth folder to calibrate on")
    x.add_argument("--n-calib", type=int, default=32)
    a = ap.parse_args(argv)
    if a.cmd == "ship":
        print(json.dumps(ship(a.run, a.calib, a.val), indent=1))
        return 0
    if a.cmd == "export":
        path = export(a.run, a.out, a.calib, a.n_calib)
        print(json.dumps({"file": str(path), "bytes": path.stat().st_size}, indent=1))
        return 0
    if a.cmd == "train":
        scores = train(a.out, a.data, a.val, a.steps, a.batch, a.lr, a.seed, a.threads, resume=a.resume, views=a.views)
        print(json.dumps(scores, indent=1))
        return 0
    if a.tiles is not None and not 0 < a.tiles <= 1:
        ap.error(f"--tiles must be in (0, 1], got {a.tiles}")
    if a.run is not None and a.onnx is not None:
        ap.error("--run and --onnx exclude each other")
    if a.run is not None:
        net = load_net(a.run)
    else:
        from monodbh.models.runtime.common import MODELS_DIR
        net = OnnxTrunkNet(a.onnx or MODELS_DIR / "trunk_net_int8.onnx")
    out: dict[str, Any] = {str(f): score_folder(net, f, a.tiles) for f in a.folders}
    if a.real is not None:
        summary, rows = score_real(net, a.real, a.tiles, a.draw)
        out["real"] = {**summary, "trunks_iou": {f"{r['photo'][:2]}#{r['trunk']}": round(r["iou"], 3)
                                                 for r in rows if r["width_px"] >= 20}}
    if isinstance(net, OnnxTrunkNet) and net.passes:
        out["ms_per_pass"] = round(1000 * net.seconds / net.passes, 1)
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
