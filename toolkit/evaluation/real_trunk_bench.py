"""Real photos with hand-drawn trunk outlines: how well the segmenter finds real trunks.

The 24 real photos of ``../shared/data/real_trees`` have no ground truth of their own. Their main
visible trunks were outlined by hand, a polygon per visible trunk segment in the photo's pixels
(``data/real_trees_outlines.json`` next to this module, with each photo's SHA-256, author,
licence and source page from the folder's MANIFEST.md). This command segments each photo with
the shipped segmenter and scores every outlined trunk at least :data:`MIN_WIDTH_PX` wide (its
area over its rows):

- ``iou``: the intersection over union of the outline with the predicted tree instance that
  overlaps it most, both taken within the outline's rows (so the crown and the limbs above the
  fork, which the outline leaves out, do not count; a neighbouring trunk merged into the
  instance at those rows does);
- ``iou_local``: the same within one trunk width either side of the outline on each of its
  rows, so a crown or a limb beside the trunk further out does not count (a segmenter that
  labels the crown "tree", as it should, is otherwise penalised wherever the crown hangs
  beside the trunk); ``recall_local`` counts the trunks found by it;
- ``recall``: a trunk is found when that IoU is at least :data:`FOUND_IOU`;
- ``pixel_recall``: the share of the outline's pixels the segmenter calls "tree" (any
  instance), and what it calls the rest (ground, vegetation, sky, ...).

``--draw DIR`` writes each photo with its outlines (yellow), the predicted tree pixels (blue)
and each trunk's IoU, to check the outlines and see the failures. ``--crop F`` segments, for each
outlined trunk, a square crop of side ``F`` x the photo's long side centred on the trunk instead
of the whole photo (:func:`score_trunk_in_crop`): how much a zoomed second pass would find.
``--trunk --net`` scores the shipped trunk network's map instead (``models/trunk_net_int8.onnx``,
what ``dbh reconstruct`` reads). ``--trunk`` scores the segmenter's trunk head instead of its "tree" instances: the trunk pixels
are those whose trunk probability reaches the segmenter's ``trunk_threshold``, the instances
their connected parts (8-neighbour), so a trunk is scored against the stem the head found, not
against a whole tree with its crown; with ``--tiles F``, the head's probability blended over
the tiles (:meth:`~monodbh.models.runtime.segmenter.Segmenter.trunk_map`), without: one pass. ``--tiles F`` segments the whole photo as overlapping square tiles of side ``F`` x its long side
(half a tile apart, :func:`segment_tiled`), without knowing where the trunks are: a pixel is
"tree" where at least half the tiles that hold it say so, and the instances are the connected
parts of that mask (so touching trunks and crowns merge, which the IoU counts).

Usage::

    python -m monodbh.toolkit.evaluation.real_trunk_bench ../shared/data/real_trees [--draw runs/real_trunks] [--json F]
        [--model OTHER_SEGMENTER.onnx] [--crop 0.4 | [--tiles 0.3] [--trunk [--net] [--threshold P]]]

Imported by nothing (a command); imports the segmenter's and the trunk network's runtimes and ``monodbh.calib``.
"""
from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from monodbh.models.runtime.segmenter import tile_boxes, tile_origins

__all__ = ["OUTLINES", "MIN_WIDTH_PX", "FOUND_IOU", "load_outlines", "rasterize", "score_trunk", "WithTrunkNet",
           "trunk_instances", "score_photo", "crop_around", "score_trunk_in_crop", "tile_origins", "segment_tiled",
           "summarise", "main"]

#: the outlines shipped with this module
OUTLINES = Path(__file__).resolve().parent / "data" / "real_trees_outlines.json"
#: trunks narrower than this (mean width over their rows, px) are not scored
MIN_WIDTH_PX = 20.0
#: a trunk counts as found when its best instance has at least this IoU with it
FOUND_IOU = 0.5


def load_outlines(path: str | Path = OUTLINES) -> dict:
    """The outlines file: ``{"photos": {name: {"size": [W, H], "sha256": ..., "trunks": [{"polygon":
    [[x, y], ...], "note": ...}, ...]}}, ...}``."""
    return json.loads(Path(path).read_text())


def rasterize(polygon: Sequence[Sequence[float]], size: tuple[int, int]) -> np.ndarray:
    """(H, W) bool mask of a polygon in pixel coordinates (pixel centres at integers), drawn
    with 1/16 px vertex precision.

    Examples
    --------
    >>> int(rasterize([[2, 2], [5, 2], [5, 5], [2, 5]], (8, 8)).sum())
    16
    """
    import cv2

    W, H = size
    m = np.zeros((H, W), np.uint8)
    pts = np.round(np.asarray(polygon, np.float64) * 16).astype(np.int32).reshape(-1, 1, 2)
    cv2.fillPoly(m, [pts], 1, lineType=cv2.LINE_8, shift=4)
    return m.astype(bool)


def score_trunk(trunk: np.ndarray, instance: np.ndarray, tree_pixels: np.ndarray,
                semantic: Optional[np.ndarray] = None, classes: Sequence[str] = ()) -> dict:
    """Scores of one outlined trunk against a segmentation.

    Parameters
    ----------
    trunk : (H, W) bool
        The outline's pixels.
    instance : (H, W) int
        Predicted tree instances (0 = none).
    tree_pixels : (H, W) bool
        Pixels predicted "tree" (any instance).
    semantic, classes : optional
        Semantic ids and their names: what the missed pixels were called.

    Returns
    -------
    dict
        ``width_px`` (area / rows), ``iou`` (best instance, within the outline's rows),
        ``iou_local`` (best instance, within one trunk width either side of the outline on each
        of its rows: the trunk's edges, not a crown or a limb beside it further out),
        ``instance`` (its id, 0 if none), ``pixel_recall``, ``missed_as`` (class -> share of
        the outline's pixels).
    """
    rows = np.nonzero(trunk.any(1))[0]
    area = int(trunk.sum())
    if area == 0:
        return {"width_px": 0.0, "iou": 0.0, "iou_local": 0.0, "instance": 0, "pixel_recall": 0.0,
                "missed_as": {}}
    band = slice(int(rows[0]), int(rows[-1]) + 1)
    t, inst = trunk[band], instance[band]
    ids, inter = np.unique(inst[t & (inst > 0)], return_counts=True)
    best_iou, best = 0.0, 0
    for k, n in zip(ids, inter):
        iou = float(n) / float(np.count_nonzero(t | (inst == k)))
        if iou > best_iou:
            best_iou, best = iou, int(k)
    win = np.zeros_like(t)
    for r in range(t.shape[0]):
        c = np.nonzero(t[r])[0]
        if len(c):
            w = int(c[-1] - c[0] + 1)
            win[r, max(0, int(c[0]) - w):int(c[-1]) + w + 1] = True
    local = 0.0
    for k in ids:
        m = (inst == k) & win
        local = max(local, float(np.count_nonzero(t & m)) / float(np.count_nonzero(t | m)))
    missed = {}
    if semantic is not None:
        sem = semantic[band][t & ~tree_pixels[band]]
        for c, n in zip(*np.unique(sem, return_counts=True)):
            name = classes[c] if c < len(classes) else ("unassigned" if c == 255 else str(int(c)))
            missed[name] = round(float(n) / area, 4)
    return {"width_px": area / len(rows), "iou": best_iou, "iou_local": local, "instance": best,
            "pixel_recall": float(np.count_nonzero(trunk & tree_pixels)) / area, "missed_as": missed}


def trunk_instances(trunk_prob: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Trunk mask ``(H, W)`` bool (probability >= ``threshold``) and its connected parts
    ``(H, W)`` int32 (8-neighbour, 0 = none), the trunk head's instances.

    Examples
    --------
    >>> p = np.zeros((4, 6)); p[:, 1] = p[:, 4] = 0.9
    >>> mask, inst = trunk_instances(p, 0.5)
    >>> int(mask.sum()), int(inst.max())
    (8, 2)
    """
    import cv2

    mask = np.asarray(trunk_prob) >= threshold
    _, inst = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    return mask, inst.astype(np.int32)


class WithTrunkNet:
    """A segmenter whose trunk map is the trunk network's (``--net``: what ``dbh reconstruct``
    reads where the network is shipped); the segmentation drawn comes from ``segmenter``."""

    def __init__(self, segmenter, trunk_net) -> None:
        self.segmenter, self.net = segmenter, trunk_net
        self.path, self.trunk_threshold = trunk_net.path, trunk_net.threshold

    def predict(self, rgb, size=None, trunk=False):
        r = self.segmenter.predict(rgb, size=size)
        if trunk:
            r.trunk_prob = self.net.trunk_map(rgb, size, None)
        return r

    def trunk_map(self, rgb, size=None, tile_frac=0.5):
        return self.net.trunk_map(rgb, size, tile_frac)


def score_photo(rgb: np.ndarray, entry: dict, segmenter, tiles: Optional[float] = None, trunk: bool = False,
                threshold: Optional[float] = None) -> tuple[list[dict], object]:
    """Segment ``rgb`` (H, W, 3) (whole, or with ``tiles`` by :func:`segment_tiled`) and score
    each outlined trunk of ``entry`` (all widths; :func:`summarise` keeps the wide ones); with
    ``trunk``, against the trunk head's instances (:func:`trunk_instances`) at ``threshold``
    (default the head's own). Returns ``(scores, segmentation)``."""
    H, W = rgb.shape[:2]
    if trunk:                                   # one pass gives the map with the segmentation
        seg = segmenter.predict(rgb, size=(W, H), trunk=not tiles)
        if tiles:
            seg.trunk_prob = segmenter.trunk_map(rgb, (W, H), tiles)
        tree, inst = trunk_instances(seg.trunk_prob, segmenter.trunk_threshold if threshold is None else threshold)
    else:
        seg = segment_tiled(rgb, segmenter, tiles) if tiles else segmenter.predict(rgb, size=(W, H))
        tree, inst = seg.semantic == seg.tree_class, seg.instance
    out = []
    for i, tr in enumerate(entry["trunks"]):
        s = score_trunk(rasterize(tr["polygon"], (W, H)), inst, tree, seg.semantic, seg.classes)
        out.append({"trunk": i, "note": tr.get("note", ""), **s})
    return out, seg


def crop_around(mask: np.ndarray, frac: float) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)``: a square of side ``frac`` x the long side of ``mask`` (H, W) bool,
    centred on the mask's centroid and shifted to lie inside the photo (cut to it where larger).

    Examples
    --------
    >>> m = np.zeros((100, 60), bool); m[40:60, 5:15] = True
    >>> crop_around(m, 0.4)
    (0, 30, 40, 70)
    """
    from monodbh.toolkit.frames import square_crop

    if not 0 < frac <= 1:
        raise ValueError(f"crop fraction must be in (0, 1], got {frac}")
    ys, xs = np.nonzero(mask)
    return square_crop((xs.mean(), ys.mean()), frac, mask.shape)


def score_trunk_in_crop(rgb: np.ndarray, polygon, segmenter, frac: float) -> dict:
    """:func:`score_trunk` of one outlined trunk, segmented in :func:`crop_around` (``frac``)
    instead of the whole photo ``rgb`` (H, W, 3). The scores are of the trunk's part inside the
    crop; ``width_px`` is the whole outline's, so that the same trunks are kept as without it."""
    H, W = rgb.shape[:2]
    trunk = rasterize(polygon, (W, H))
    if not trunk.any():
        return score_trunk(trunk, np.zeros((H, W), np.int32), np.zeros((H, W), bool))
    x0, y0, x1, y1 = crop_around(trunk, frac)
    seg = segmenter.predict(np.ascontiguousarray(rgb[y0:y1, x0:x1]), size=(x1 - x0, y1 - y0))
    out = score_trunk(trunk[y0:y1, x0:x1], seg.instance, seg.semantic == seg.tree_class, seg.semantic,
                      seg.classes)
    out["width_px"] = float(trunk.sum()) / float(np.count_nonzero(trunk.any(1)))
    return out


def segment_tiled(rgb: np.ndarray, segmenter, frac: float, vote: float = 0.5):
    """Segment ``rgb`` (H, W, 3) uint8 as square tiles of side ``frac`` x its long side, half a
    tile apart (:func:`tile_origins`), each at the segmenter's own input size.

    Returns an object with the fields of a segmentation (``instance`` (H, W) int32,
    ``semantic`` (H, W) uint8, ``tree_class``, ``classes``): "tree" where at least ``vote`` of
    the tiles holding the pixel say so, instances the 8-connected parts of that mask; the other
    pixels keep the whole photo's classes (its "tree" pixels outside the tiled mask become
    unassigned, 255).
    """
    import cv2
    from types import SimpleNamespace

    H, W = rgb.shape[:2]
    votes = np.zeros((H, W), np.float32)
    cover = np.zeros((H, W), np.float32)
    for y0, y1, x0, x1 in tile_boxes(H, W, frac):
        r = segmenter.predict(np.ascontiguousarray(rgb[y0:y1, x0:x1]), size=(x1 - x0, y1 - y0))
        votes[y0:y1, x0:x1] += r.semantic == r.tree_class
        cover[y0:y1, x0:x1] += 1.0
    whole = segmenter.predict(rgb, size=(W, H))
    tree = votes >= vote * cover
    _, inst = cv2.connectedComponents(tree.astype(np.uint8), connectivity=8)
    sem = np.asarray(whole.semantic, np.uint8).copy()
    sem[~tree & (sem == whole.tree_class)] = 255
    sem[tree] = whole.tree_class
    return SimpleNamespace(instance=inst.astype(np.int32), semantic=sem, tree_class=whole.tree_class,
                           classes=whole.classes)


def summarise(rows: Sequence[dict], min_width_px: float = MIN_WIDTH_PX) -> dict:
    """Mean IoU, recall (IoU >= :data:`FOUND_IOU`), mean pixel recall and what the missed
    pixels were called, over the trunks at least ``min_width_px`` wide."""
    wide = [r for r in rows if r["width_px"] >= min_width_px]
    if not wide:
        return {"trunks": 0}
    missed: dict[str, float] = {}
    for r in wide:
        for k, v in r["missed_as"].items():
            missed[k] = missed.get(k, 0.0) + v / len(wide)
    return {"trunks": len(wide), "narrow_skipped": len(rows) - len(wide),
            "iou_mean": float(np.mean([r["iou"] for r in wide])),
            "iou_median": float(np.median([r["iou"] for r in wide])),
            "recall": float(np.mean([r["iou"] >= FOUND_IOU for r in wide])),
            "iou_local_mean": float(np.mean([r["iou_local"] for r in wide])),
            "recall_local": float(np.mean([r["iou_local"] >= FOUND_IOU for r in wide])),
            "pixel_recall_mean": float(np.mean([r["pixel_recall"] for r in wide])),
            "missed_as": {k: round(v, 4) for k, v in sorted(missed.items(), key=lambda kv: -kv[1])}}


def _draw(rgb: np.ndarray, entry: dict, scores: Sequence[dict], seg, path: Path,
          tree: Optional[np.ndarray] = None) -> None:
    import cv2

    img = rgb.astype(np.float32).copy()
    tree = seg.semantic == seg.tree_class if tree is None else tree
    img[tree] = 0.55 * img[tree] + 0.45 * np.array([40, 110, 255], np.float32)
    img = np.ascontiguousarray(img.clip(0, 255).astype(np.uint8))
    lw = max(1, round(max(img.shape[:2]) / 600))
    for tr, s in zip(entry["trunks"], scores):
        pts = np.round(np.asarray(tr["polygon"]) * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(img, [pts], True, (255, 230, 0), lw, cv2.LINE_AA, shift=4)
        x, y = np.asarray(tr["polygon"]).mean(0)
        label = f"{s['iou']:.2f}" if s["width_px"] >= MIN_WIDTH_PX else "narrow"
        cv2.putText(img, label, (int(x) - 14, int(y)), cv2.FONT_HERSHEY_SIMPLEX, 0.45 * lw, (0, 0, 0), 3 * lw)
        cv2.putText(img, label, (int(x) - 14, int(y)), cv2.FONT_HERSHEY_SIMPLEX, 0.45 * lw, (255, 255, 255), lw)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))


def run(folder: Path, outlines: dict, draw: Optional[Path] = None, segmenter=None,
        crop: Optional[float] = None, tiles: Optional[float] = None, trunk: bool = False,
        threshold: Optional[float] = None) -> list[dict]:
    """Score every outlined photo of ``folder``; a row per trunk (``photo`` added); with
    ``crop``, each trunk in its own crop (:func:`score_trunk_in_crop`, no drawing); with
    ``tiles``, the photo segmented in tiles (:func:`segment_tiled`); with ``trunk``, the trunk
    head's trunks (:func:`trunk_instances`, in ``tiles`` if given; drawn in blue instead of the
    "tree" pixels)."""
    from monodbh.calib import load_photo
    from monodbh.models.runtime.segmenter import Segmenter

    seg_net = segmenter or Segmenter()
    rows = []
    for name, entry in sorted(outlines["photos"].items()):
        p = Path(folder) / name
        if not p.is_file():
            print(f"{p}: missing, skipped")
            continue
        if entry.get("sha256") and hashlib.sha256(p.read_bytes()).hexdigest() != entry["sha256"]:
            print(f"{p}: not the outlined photo (SHA-256 differs), skipped")
            continue
        rgb = load_photo(p)
        if [rgb.shape[1], rgb.shape[0]] != list(entry["size"]):
            print(f"{p}: {rgb.shape[1]}x{rgb.shape[0]} px, outlined at {entry['size']}, skipped")
            continue
        if crop is not None:
            rows += [{"photo": name, "trunk": i, "note": tr.get("note", ""),
                      **score_trunk_in_crop(rgb, tr["polygon"], seg_net, crop)}
                     for i, tr in enumerate(entry["trunks"])]
            continue
        scores, seg = score_photo(rgb, entry, seg_net, tiles, trunk, threshold)
        rows += [{"photo": name, **s} for s in scores]
        if draw is not None:
            t = seg_net.trunk_threshold if threshold is None else threshold
            mask = trunk_instances(seg.trunk_prob, t)[0] if trunk else None
            _draw(rgb, entry, scores, seg, Path(draw) / f"{p.stem}_outlines.png", mask)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m monodbh.toolkit.evaluation.real_trunk_bench",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("folder", type=Path, help="the real photos (../shared/data/real_trees)")
    ap.add_argument("--outlines", type=Path, default=OUTLINES)
    ap.add_argument("--draw", type=Path, help="write <photo>_outlines.png here")
    ap.add_argument("--json", type=Path, help="write the per-trunk rows and the summary here")
    ap.add_argument("--model", type=Path, help="a segmenter ONNX file other than the shipped one")
    ap.add_argument("--crop", type=float, metavar="F",
                    help="segment a square crop of side F x the photo's long side around each trunk")
    ap.add_argument("--tiles", type=float, metavar="F",
                    help="segment the whole photo in overlapping square tiles of side F x its long side")
    ap.add_argument("--trunk", action="store_true",
                    help="score the segmenter's trunk head (its trunks) instead of its tree instances")
    ap.add_argument("--net", action="store_true",
                    help="with --trunk: the shipped trunk network's map (dbh reconstruct's) instead of the trunk head's")
    ap.add_argument("--threshold", type=float, metavar="P",
                    help="with --trunk: trunk pixels from this probability on (default the head's, 0.5)")
    a = ap.parse_args(argv)
    if a.threshold is not None and not (a.trunk and 0 < a.threshold < 1):
        ap.error("--threshold needs --trunk and a probability in (0, 1)")
    if a.crop is not None and (a.tiles is not None or a.trunk):
        ap.error("--crop excludes --tiles and --trunk")
    for flag, v in (("--crop", a.crop), ("--tiles", a.tiles)):
        if v is not None and not 0 < v <= 1:
            ap.error(f"{flag} must be in (0, 1], got {v}")
    seg = None
    if a.model is not None:
        from monodbh.models.runtime.segmenter import Segmenter
        seg = Segmenter(a.model)
    if a.net and not a.trunk:
        ap.error("--net needs --trunk")
    if a.net:
        from monodbh.models.runtime.segmenter import Segmenter
        from monodbh.models.runtime.trunk_net import TrunkNet
        seg = WithTrunkNet(seg or Segmenter(trunk_head=None), TrunkNet())
    elif a.trunk:
        from monodbh.models.runtime.segmenter import Segmenter
        seg = seg or Segmenter()
        if not seg.has_trunk:
            ap.error(f"{seg.path}: this segmenter has no trunk head")
    rows = run(a.folder, load_outlines(a.outlines), a.draw, segmenter=seg, crop=a.crop, tiles=a.tiles,
               trunk=a.trunk, threshold=a.threshold)
    print("| photo | trunks >= 20 px | mean IoU | found (IoU >= 0.5) | local IoU | found by it | pixel recall |\n"
          "|---|---|---|---|---|---|---|")
    for name in sorted({r["photo"] for r in rows}):
        s = summarise([r for r in rows if r["photo"] == name])
        if s["trunks"]:
            print(f"| {name} | {s['trunks']} | {s['iou_mean']:.2f} | {s['recall'] * s['trunks']:.0f} | "
                  f"{s['iou_local_mean']:.2f} | {s['recall_local'] * s['trunks']:.0f} | {s['pixel_recall_mean']:.2f} |")
        else:
            print(f"| {name} | 0 | - | - | - | - | - |")
    s = summarise(rows)
    if s["trunks"]:
        print(f"\n{s['trunks']} trunks >= {MIN_WIDTH_PX:g} px ({s['narrow_skipped']} narrower skipped): "
              f"mean IoU {s['iou_mean']:.3f} (median {s['iou_median']:.3f}), recall {s['recall']:.3f}, "
              f"local IoU {s['iou_local_mean']:.3f}, recall {s['recall_local']:.3f}, "
              f"pixel recall {s['pixel_recall_mean']:.3f}; missed pixels called: "
              + ", ".join(f"{k} {v:.3f}" for k, v in s["missed_as"].items()))
    if a.json:
        from monodbh.toolkit.outputs.atomic import atomic_write_text

        atomic_write_text(a.json, json.dumps({"rows": rows, "summary": s}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
