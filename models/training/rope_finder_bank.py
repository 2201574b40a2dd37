"""Example banks of the rope finder (training only): ``python -m monodbh.models.training.rope_finder_bank``.

Each photo of a ``dbh synth`` folder gives ``TILE`` x ``TILE`` crops of the photo with the
rope's visible pixels (the sample's ``rope`` mask) as the target, at the network's output
resolution (a 2 x 2 max: a 1 px rope is one output pixel wide):

* ``n_pos`` crops holding the rope's middle at a random place (not within ``MARGIN`` of the
  crop's border);
* one crop centred on the reddest place of the photo that is not the rope (red jackets,
  flagging tape, red bark in the light: what the finder must learn to leave alone);
* one on a random place of a trunk (the segmentation's tree instances) and ``n_rand`` anywhere;
* with ``--mine MODEL`` instead (hard negatives, :func:`cut_folder` with ``mine``): crops centred on the
  places a trained finder takes for rope and are not (its candidates away from the true rope:
  tape, paint marks, red leaves, bark), to train the next finder on.

Usage::

    python -m monodbh.models.training.rope_finder_bank data/tex_train data/rope_finder/tex_train.npz

Arrays: ``rgb`` (N, TILE, TILE, 3) uint8, ``target`` (N, TILE/2, TILE/2) uint8 (1 rope, 0 not),
``photo`` (N,) index in the folder, ``kind`` (N,) 0 rope / 1 reddest / 2 trunk / 3 random /
4 mined.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

__all__ = ["TILE", "MARGIN", "cut_photo", "cut_folder", "mine_photo"]

TILE: int = 192        #: crop side in photo pixels (the finder's ONNX tile)
MARGIN: int = 24       #: the rope's middle stays this far from a positive crop's border


def _crop(a: np.ndarray, x0: int, y0: int) -> np.ndarray:
    H, W = a.shape[:2]
    out = np.zeros((TILE, TILE) + a.shape[2:], a.dtype)
    xa, ya = max(0, x0), max(0, y0)
    xb, yb = min(W, x0 + TILE), min(H, y0 + TILE)
    if xb > xa and yb > ya:
        out[ya - y0:yb - y0, xa - x0:xb - x0] = a[ya:yb, xa:xb]
    return out


def _target(rope: np.ndarray) -> np.ndarray:
    """(TILE, TILE) bool -> (TILE/2, TILE/2) uint8, a 2 x 2 max."""
    r = rope.reshape(TILE // 2, 2, TILE // 2, 2)
    return r.max(axis=(1, 3)).astype(np.uint8)


def _redness(rgb: np.ndarray) -> np.ndarray:
    f = rgb.astype(np.float32)
    r, g, b = f[..., 0], f[..., 1], f[..., 2]
    return cv2.blur((r - np.maximum(g, b)) / (r + g + b + 30.0), (5, 5))


def cut_photo(rgb: np.ndarray, rope: np.ndarray, instance: np.ndarray, rng: np.random.Generator,
              n_pos: int = 3, n_rand: int = 2) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """Crops ``(rgb (T, T, 3), target (T/2, T/2), kind)`` of one photo (see the module docstring).

    Crop corners are even, so the target's 2 x 2 cells line up with the network's output.
    """
    H, W = rope.shape
    out = []

    def add(cx: float, cy: float, kind: int, jitter: int = 0) -> None:
        x0 = int(round(cx - TILE / 2 + (rng.integers(-jitter, jitter + 1) if jitter else 0))) // 2 * 2
        y0 = int(round(cy - TILE / 2 + (rng.integers(-jitter, jitter + 1) if jitter else 0))) // 2 * 2
        x0 = int(np.clip(x0, -TILE // 4, W - 3 * TILE // 4)) // 2 * 2
        y0 = int(np.clip(y0, -TILE // 4, H - 3 * TILE // 4)) // 2 * 2
        out.append((_crop(rgb, x0, y0), _target(_crop(rope, x0, y0)), kind))

    ys, xs = np.nonzero(rope)
    if len(xs):
        cx, cy = float(np.median(xs)), float(np.median(ys))
        for _ in range(n_pos):
            add(cx, cy, 0, jitter=TILE // 2 - MARGIN)
    red = _redness(rgb)
    if len(xs):
        red[cv2.dilate(rope.astype(np.uint8), np.ones((31, 31), np.uint8)) > 0] = -1.0
    ry, rx = np.unravel_index(int(np.argmax(red)), red.shape)
    add(rx, ry, 1, jitter=TILE // 4)
    ty, tx = np.nonzero(instance[::4, ::4] > 0)
    if len(tx):
        k = int(rng.integers(len(tx)))
        add(4 * tx[k], 4 * ty[k], 2)
    for _ in range(n_rand):
        add(rng.uniform(0, W), rng.uniform(0, H), 3)
    return out


def mine_photo(rgb: np.ndarray, rope: np.ndarray, finder, rng: np.random.Generator, min_peak: float = 1.5,
               far_px: float = 12.0, n_max: int = 4) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """Crops (kind 4) centred on ``finder``'s candidates with log-odds >= ``min_peak`` lying
    more than ``far_px`` from every rope pixel (hard negatives), at most ``n_max``."""
    H, W = rope.shape
    ys, xs = np.nonzero(rope)
    out = []
    for c in finder.components(rgb):
        if c.peak < min_peak or len(out) >= n_max:
            continue
        if len(xs) and np.min(np.hypot(xs - c.center_xy[0], ys - c.center_xy[1])) <= far_px:
            continue
        j = TILE // 4
        x0 = int(np.clip(round(c.center_xy[0] - TILE / 2 + rng.integers(-j, j + 1)), -TILE // 4, W - 3 * TILE // 4)) // 2 * 2
        y0 = int(np.clip(round(c.center_xy[1] - TILE / 2 + rng.integers(-j, j + 1)), -TILE // 4, H - 3 * TILE // 4)) // 2 * 2
        out.append((_crop(rgb, x0, y0), _target(_crop(rope, x0, y0)), 4))
    return out


def cut_folder(folder: str | Path, out: str | Path, seed: int = 0, limit: int | None = None,
               mine: str | None = None, allow_heldout: bool = False) -> dict:
    """Cut every photo of a ``dbh synth`` folder into the bank ``out`` (``.npz``); with ``mine``
    (a finder ONNX file), its hard negatives instead (:func:`mine_photo`). A folder of the
    held-out look is refused unless ``allow_heldout`` (a bank to evaluate on, not to train)."""
    folder = Path(folder)
    photos = sorted(folder.glob("*.jpg"))[:limit]
    if not photos:
        raise FileNotFoundError(f"{folder}: no .jpg samples")
    if not allow_heldout:
        from .common import refuse_heldout
        refuse_heldout(folder, [json.loads(p.with_suffix(".json").read_text()) for p in (photos[0], photos[-1])
                                if p.with_suffix(".json").exists()])
    finder = None
    if mine:
        from monodbh.models.runtime.rope_finder import RopeFinder
        finder = RopeFinder(mine, threads=1)
    rgbs, tgts, idx, kinds = [], [], [], []
    for i, p in enumerate(photos):
        rng = np.random.default_rng([seed, i, 41])
        bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if bgr is None:
            print(f"{p}: unreadable, skipped", file=sys.stderr)
            continue
        with np.load(p.with_suffix(".npz")) as z:
            rope, inst = z["rope"].astype(bool), z["instance"]
        rgb0 = np.ascontiguousarray(bgr[..., ::-1])
        crops = mine_photo(rgb0, rope, finder, rng) if finder is not None else cut_photo(rgb0, rope, inst, rng)
        for rgb, t, k in crops:
            rgbs.append(rgb)
            tgts.append(t)
            idx.append(int(p.stem))
            kinds.append(k)
        if (i + 1) % 100 == 0:
            print(f"{folder}: {i + 1}/{len(photos)} photos, {len(rgbs)} crops", flush=True)
    if not rgbs:
        raise ValueError(f"{folder}: no crops cut")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp.npz")
    np.savez(tmp, rgb=np.stack(rgbs), target=np.stack(tgts), photo=np.array(idx, np.int64),
             kind=np.array(kinds, np.int64))
    tmp.replace(out)
    info = {"folder": str(folder), "photos": len(photos), "crops": len(rgbs),
            "rope_crops": int(sum(k == 0 for k in kinds))}
    print(json.dumps(info))
    return info


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("folder")
    ap.add_argument("out")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--mine", default=None, help="a trained finder (.onnx): cut its hard negatives instead")
    a = ap.parse_args(argv)
    cut_folder(a.folder, a.out, a.seed, a.limit, a.mine)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
