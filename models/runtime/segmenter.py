"""The segmenter's runtime (network kind ``segmenter``): tree instances and stuff masks of a photo.

The Mask2Former-style network gives per-query class and mask logits; :func:`panoptic_merge`
turns them into non-overlapping segments (greedy, as Mask2Former's panoptic inference), and
:meth:`Segmenter.predict` into a :class:`SegmentationResult`. Imported by ``monodbh.toolkit``
and the segmenter's training code (``panoptic_merge`` scores it on the runtime's path); imports
numpy, cv2 and ``monodbh.models.runtime.common`` only.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from monodbh.models.runtime.common import MonodbhError, OnnxPredictor

__all__ = ["FEATURES_OUTPUT", "TRUNK_TILE_FRAC", "TRUNK_TILE_BLEND", "SegmentationResult", "panoptic_merge",
           "trunk_probability", "tile_origins", "tile_boxes", "tile_weight", "blend_tiles", "Segmenter"]

#: the segmenter's per-pixel embedding (``(1, D, S/4, S/4)``), an output of files that feed a
#: trunk head; computed in every run, copied out only when asked for
FEATURES_OUTPUT = "mask_features"
#: trunk maps blend the trunk head's over square tiles of this fraction of the photo's long side,
#: half a tile apart (``docs/decisions/trunk-head.md``: chosen on synthetic 1280 x 960 photos,
#: trunk IoU 0.804 whole, 0.825 at 0.5, 0.726 at 0.3)
TRUNK_TILE_FRAC = 0.5
#: how the tiles are blended: ``"tent"`` weighted by :func:`tile_weight` (no seams where a tile
#: ends; 0.867 -> 0.871 and 0.737 -> 0.755 on synthetic 1280 x 960 photos in both looks against
#: ``"mean"``, the plain mean; ``docs/decisions/trunk-head.md``)
TRUNK_TILE_BLEND = "tent"


@dataclass
class SegmentationResult:
    """Output of :meth:`Segmenter.predict` (all maps at ``size`` = (W, H)).

    Attributes
    ----------
    instance : (H, W) uint16
        0 = no tree, k = tree ``k`` (1-based, trees sorted by decreasing score).
    semantic : (H, W) uint8
        Semantic id per pixel (0 sky, 1 ground, 2 other vegetation, 3 tree, 4 other;
        255 = unassigned).
    tree_scores : (N,) float32
        Score of tree ``k`` at index ``k - 1``: class probability x mean mask probability.
    classes : tuple of str
        Class names by semantic id.
    trunk_prob : (H, W) float32 or None
        Probability that the pixel is a trunk (a tree's stem, the rope on it included; not its
        branches or foliage), from the segmenter's trunk head; None unless asked for
        (:meth:`Segmenter.predict` ``trunk=True``) and shipped.

    ``tree_masks`` (N, H, W) bool and ``stuff_masks`` (name -> (H, W) bool) are derived on
    demand (a 12 MP photo with 40 trees would need 480 MB of masks).
    """

    instance: np.ndarray
    semantic: np.ndarray
    tree_scores: np.ndarray
    classes: tuple[str, ...] = field(default_factory=tuple)
    tree_class: int = 3
    trunk_prob: np.ndarray | None = None

    @property
    def size(self) -> tuple[int, int]:
        return (self.semantic.shape[1], self.semantic.shape[0])

    @property
    def n_trees(self) -> int:
        return int(len(self.tree_scores))

    def tree_mask(self, k: int) -> np.ndarray:
        """(H, W) bool mask of tree ``k`` (1-based)."""
        return self.instance == k

    @property
    def tree_masks(self) -> np.ndarray:
        """(N, H, W) bool, one per tree (non-overlapping), by decreasing score."""
        H, W = self.instance.shape
        out = np.zeros((self.n_trees, H, W), bool)
        for k in range(self.n_trees):
            out[k] = self.instance == k + 1
        return out

    @property
    def stuff_masks(self) -> dict[str, np.ndarray]:
        """Class name -> (H, W) bool for the stuff classes present."""
        out = {}
        for c in np.unique(self.semantic):
            if c == 255 or c == self.tree_class:
                continue
            name = self.classes[c] if c < len(self.classes) else str(int(c))
            out[name] = self.semantic == c
        return out


def _sigmoid(x: np.ndarray) -> np.ndarray:
    """Logistic function, float32, computed in place on a copy (fewer temporaries)."""
    y = np.clip(x, -50, 50).astype(np.float32, copy=False)
    np.negative(y, out=y)
    np.exp(y, out=y)
    y += 1.0
    np.reciprocal(y, out=y)
    return y


def _softmax(x: np.ndarray) -> np.ndarray:
    e = np.exp(x - x.max(-1, keepdims=True))
    return e / e.sum(-1, keepdims=True)


def panoptic_merge(class_logits: np.ndarray, mask_logits: np.ndarray, size: tuple[int, int],
                   thing_classes: tuple[int, ...] = (3,), score_threshold: float = 0.5,
                   overlap_threshold: float = 0.8, mask_threshold: float = 0.5,
                   work_max_side: int | None = 640) -> dict[str, Any]:
    """Mask2Former panoptic inference: greedy, non-overlapping segments.

    Parameters
    ----------
    class_logits : (Q, C + 1)
        Last class is "no object".
    mask_logits : (Q, h, w)
    size : (W, H)
        Output resolution.
    thing_classes : tuple of int
        Classes whose queries become separate instances (tree); others merge per class.
    score_threshold : float
        Min class probability of a kept query (Mask2Former ``object_mask_threshold``, 0.8 there).
    overlap_threshold : float
        Min fraction of a query's own mask that survives the arg-max (Mask2Former default 0.8).
    work_max_side : int or None
        Masks are bilinearly upsampled (logit space) to a working resolution whose long side is
        at most this, merged there, and the segment map is resized to ``size`` with nearest
        neighbour (the logits are 1/4 of the network input, so a finer working grid adds no
        information; 640 costs 150 ms for ~50 kept queries vs 340 ms at 1024). ``None``: merge
        at ``size``.

    Returns
    -------
    dict
        ``segments``: list of ``{"id", "label", "score", "isthing", "query", "mask_prob"}``
        (``mask_prob`` = mean mask probability inside the segment); ``panoptic`` (H, W) int32
        segment id per pixel (0 = none).
    """
    W, H = int(size[0]), int(size[1])
    w, h = _work_size(W, H, work_max_side)
    probs = _softmax(class_logits.astype(np.float32))
    labels = probs.argmax(-1)
    scores = probs.max(-1)
    keep = np.nonzero((labels != class_logits.shape[-1] - 1) & (scores > score_threshold))[0]
    if keep.size == 0:
        return {"segments": [], "panoptic": np.zeros((H, W), np.int32)}
    owner, best_p, orig_area = _owner_pass(mask_logits, keep, scores, (w, h), mask_threshold)
    valid = (owner >= 0) & (best_p >= mask_threshold)
    lut, segments = _segment_table(keep, labels, scores, owner, best_p, valid, orig_area,
                                   thing_classes, overlap_threshold)
    pan = np.where(valid, lut[owner + 1], 0).astype(np.int32)
    if (w, h) != (W, H):
        pan = cv2.resize(pan, (W, H), interpolation=cv2.INTER_NEAREST)
    return {"segments": segments, "panoptic": pan}


def _work_size(W: int, H: int, work_max_side: int | None) -> tuple[int, int]:
    """(w, h) of the merging grid: (W, H) scaled so its long side is at most ``work_max_side``."""
    if work_max_side and max(W, H) > work_max_side:
        f = work_max_side / max(W, H)
        return max(1, int(round(W * f))), max(1, int(round(H * f)))
    return W, H


def _owner_pass(mask_logits: np.ndarray, keep: np.ndarray, scores: np.ndarray,
                work_wh: tuple[int, int], mask_threshold: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One pass over the kept queries at the working size.

    Returns ``owner`` (h, w) int32, the index into ``keep`` of the query with the highest
    score * probability (-1 where none), ``best_p`` (h, w) that query's probability, and
    ``orig_area`` (K,) each query's own mask area before the arg-max.
    """
    w, h = work_wh
    best = np.zeros((h, w), np.float32)
    best_p = np.zeros((h, w), np.float32)
    owner = np.full((h, w), -1, np.int32)
    orig_area = np.zeros(len(keep), np.int64)
    for j, q in enumerate(keep):
        m = mask_logits[q].astype(np.float32)
        if m.shape != (h, w):
            m = cv2.resize(m, (w, h), interpolation=cv2.INTER_LINEAR)
        p = _sigmoid(m)
        orig_area[j] = int(np.count_nonzero(p >= mask_threshold))
        v = p * scores[q]
        upd = v > best
        best[upd] = v[upd]
        best_p[upd] = p[upd]
        owner[upd] = j
    return owner, best_p, orig_area


def _segment_table(keep: np.ndarray, labels: np.ndarray, scores: np.ndarray, owner: np.ndarray,
                   best_p: np.ndarray, valid: np.ndarray, orig_area: np.ndarray,
                   thing_classes: tuple[int, ...], overlap_threshold: float
                   ) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """Segments of the queries that keep enough of their mask; stuff queries merge per class.

    Returns ``lut`` (K + 1,) int32, segment id of owner index ``j`` at ``j + 1`` (0: none), and
    the segment list of :func:`panoptic_merge`.
    """
    own_area = np.bincount(owner[owner >= 0], minlength=len(keep))
    final_area = np.bincount(owner[valid], minlength=len(keep))
    prob_sum = np.bincount(owner[valid], weights=best_p[valid], minlength=len(keep))
    lut = np.zeros(len(keep) + 1, np.int32)
    segments: list[dict[str, Any]] = []
    stuff_ids: dict[int, int] = {}
    next_id = 1
    for j, q in enumerate(keep):
        lab = int(labels[q])
        isthing = lab in thing_classes
        if own_area[j] == 0 or orig_area[j] == 0 or final_area[j] == 0:
            continue
        if own_area[j] / orig_area[j] < overlap_threshold:
            continue
        if not isthing and lab in stuff_ids:
            lut[j + 1] = stuff_ids[lab]
            continue
        lut[j + 1] = next_id
        if not isthing:
            stuff_ids[lab] = next_id
        segments.append({"id": next_id, "label": lab, "score": float(scores[q]),
                         "isthing": isthing, "query": int(q),
                         "mask_prob": float(prob_sum[j] / final_area[j])})
        next_id += 1
    return lut, segments


def tile_origins(length: int, side: int) -> list[int]:
    """Start offsets of tiles of ``side`` px, half a tile apart, covering ``length`` px (the last
    one flush with the end; one tile at 0 where ``side >= length``).

    Examples
    --------
    >>> tile_origins(100, 40)
    [0, 20, 40, 60]
    >>> tile_origins(100, 45)
    [0, 22, 44, 55]
    >>> tile_origins(30, 40)
    [0]
    """
    if side >= length:
        return [0]
    step = max(1, side // 2)
    out = list(range(0, length - side + 1, step))
    if out[-1] + side < length:
        out.append(length - side)
    return out


def tile_boxes(height: int, width: int, frac: float) -> list[tuple[int, int, int, int]]:
    """``(y0, y1, x0, x1)`` of the square tiles of side ``frac`` x the long side of a
    ``(height, width)`` photo, half a tile apart (:func:`tile_origins`), clipped to the photo.

    Examples
    --------
    >>> tile_boxes(60, 100, 0.5)
    [(0, 50, 0, 50), (0, 50, 25, 75), (0, 50, 50, 100), (10, 60, 0, 50), (10, 60, 25, 75), (10, 60, 50, 100)]
    """
    if not 0 < frac <= 1:
        raise ValueError(f"tile fraction must be in (0, 1], got {frac}")
    side = int(round(frac * max(height, width)))
    return [(y0, min(height, y0 + side), x0, min(width, x0 + side))
            for y0 in tile_origins(height, side) for x0 in tile_origins(width, side)]


def tile_weight(box: tuple[int, int, int, int], height: int, width: int) -> np.ndarray:
    """Blending weight ``(y1 - y0, x1 - x0)`` float32 of a tile ``box`` = ``(y0, y1, x0, x1)``
    of a ``(height, width)`` photo (:func:`tile_boxes`): a tent rising from the tile's border to
    its middle along each axis, flat on a side that lies on the photo's border (no other tile
    covers it), never below 1e-3 along an axis. Tiles half a tile apart cross-fade linearly, so
    the blend has no seams where a tile ends, and each pixel leans on the tile that sees most
    around it.

    Examples
    --------
    >>> w = tile_weight((0, 4, 2, 6), 8, 8)
    >>> w.shape, [round(float(v), 2) for v in w[0]]          # columns 2-5: tapered both ways
    ((4, 4), [0.25, 0.75, 0.75, 0.25])
    >>> [round(float(v), 2) for v in w[:, 1] / w[0, 1]]       # rows 0-3: flat on the photo's top
    [1.0, 1.0, 0.75, 0.25]
    """
    def ramp(a: int, b: int, n: int) -> np.ndarray:
        t = (np.arange(a, b, dtype=np.float32) + 0.5 - a) / max(b - a, 1)
        up = np.ones_like(t) if a == 0 else np.minimum(1.0, 2.0 * t)
        down = np.ones_like(t) if b == n else np.minimum(1.0, 2.0 * (1.0 - t))
        return np.maximum(np.minimum(up, down), 1e-3)
    y0, y1, x0, x1 = box
    return np.outer(ramp(y0, y1, height), ramp(x0, x1, width)).astype(np.float32)


def blend_tiles(rgb: np.ndarray, logits_of, size: tuple[int, int] | None = None,
                tile_frac: float | None = TRUNK_TILE_FRAC) -> np.ndarray:
    """Probability ``(H, W)`` float32 of a photo ``(H, W, 3)`` at ``size`` = (W, H) (default the
    photo's) from ``logits_of(image) -> (h, w) logits``: over square tiles of side ``tile_frac`` x
    the long side, half a tile apart (:func:`tile_boxes`), each upsampled in logit space
    (:func:`trunk_probability`) and blended by :func:`tile_weight` (:data:`TRUNK_TILE_BLEND`);
    None: one pass over the whole photo.

    Examples
    --------
    >>> rgb = np.zeros((60, 80, 3), np.uint8)
    >>> p = blend_tiles(rgb, lambda im: np.zeros((4, 4), np.float32), tile_frac=0.5)
    >>> p.shape, float(p.min()), float(p.max())
    ((60, 80), 0.5, 0.5)
    """
    H, W = rgb.shape[:2]
    if tile_frac is None:
        prob = trunk_probability(logits_of(rgb), (W, H))
    else:
        total = np.zeros((H, W), np.float32)
        cover = np.zeros((H, W), np.float32)
        for box in tile_boxes(H, W, tile_frac):
            y0, y1, x0, x1 = box
            lg = logits_of(np.ascontiguousarray(rgb[y0:y1, x0:x1]))
            w = {"tent": tile_weight, "mean": lambda *_: 1.0}[TRUNK_TILE_BLEND](box, H, W)
            total[y0:y1, x0:x1] += w * trunk_probability(lg, (x1 - x0, y1 - y0))
            cover[y0:y1, x0:x1] += w
        prob = total / cover
    size = size or (W, H)
    if (W, H) != tuple(size):
        prob = cv2.resize(prob, (int(size[0]), int(size[1])), interpolation=cv2.INTER_LINEAR)
    return prob


def trunk_probability(logits: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Trunk logits ``(h, w)`` -> probability ``(H, W)`` float32 at ``size`` = (W, H), upsampled
    bilinearly in logit space (as the masks are).

    Examples
    --------
    >>> trunk_probability(np.zeros((4, 4), np.float32), (8, 6)).shape
    (6, 8)
    """
    if logits.ndim != 2:
        raise ValueError(f"expected trunk logits (h, w), got shape {logits.shape}")
    up = cv2.resize(np.ascontiguousarray(logits, np.float32), (int(size[0]), int(size[1])),
                    interpolation=cv2.INTER_LINEAR)
    return _sigmoid(up)


class Segmenter(OnnxPredictor):
    """Tree instance + stuff segmentation (Mask2Former-style network, kind ``"segmenter"``).

    Outputs of the network: ``class_logits`` (1, Q, C + 1), ``mask_logits`` (1, Q, h, w).

    Parameters
    ----------
    path : path, optional
        ONNX file; default the shipped ``models/segmenter_int8.onnx``.
    threads, manifest, spin : as :class:`~monodbh.models.runtime.common.OnnxPredictor`.
    trunk_head : "shipped", path, TrunkHead or None
        The trunk head for ``trunk=True`` (:meth:`predict`): ``"shipped"`` (the default) the
        manifest's ``trunk_head`` where the segmenter is the shipped one; a file or a loaded
        head; None: none. Loaded on first use.
    """

    kind = "segmenter"

    def __init__(self, path: str | os.PathLike | None = None, threads: int = 2,
                 manifest: dict[str, Any] | None = None, *, spin: bool = False,
                 trunk_head: Any = "shipped") -> None:
        super().__init__("segmenter", path, threads, manifest, spin=spin)
        self._head = None
        self._head_source = None if (trunk_head == "shipped" and path is not None) else trunk_head
        self._manifest, self._threads = manifest, threads
        self.classes = tuple(self.spec.get("classes") or ())
        self.tree_class = int(self.spec.get("extra", {}).get("tree_class", 3))

    @property
    def has_trunk(self) -> bool:
        """Whether a trunk map can be given: the file exposes ``mask_features`` and a trunk head
        is shipped with it (:class:`~monodbh.models.runtime.trunk_head.TrunkHead`)."""
        return FEATURES_OUTPUT in self.output_names and self._trunk_head() is not None

    @property
    def trunk_threshold(self) -> float:
        """Trunk probability from which a pixel counts as trunk (the trunk head's threshold)."""
        head = self._trunk_head()
        return head.threshold if head is not None else 0.5

    def _trunk_head(self):
        """The trunk head (loaded on first use), or None where none is shipped."""
        if self._head is None and self._head_source is not None:
            from monodbh.models.runtime.trunk_head import TrunkHead
            src, self._head_source = self._head_source, None
            if isinstance(src, TrunkHead):
                self._head = src
            elif src == "shipped":
                from monodbh.models.runtime.common import load_manifest
                man = self._manifest if self._manifest is not None else load_manifest()
                if "trunk_head" in man.get("models", {}):
                    self._head = TrunkHead(threads=self._threads, manifest=man)
            else:
                self._head = TrunkHead(src, threads=self._threads)
        return self._head

    def raw(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Network outputs for a photo: ``(class_logits (Q, C+1), mask_logits (Q, h, w))``."""
        cls, msk = self.session.run(["class_logits", "mask_logits"],
                                    {"image": self.preprocess(rgb, "image")})
        return cls[0], msk[0]

    def raw_with_trunk(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`raw` and the trunk head's logits ``(h, w)`` from the same run of the network.

        Raises
        ------
        MonodbhError
            No trunk head for this segmenter.
        """
        if not self.has_trunk:
            raise MonodbhError(f"{self.path}: this segmenter has no trunk head "
                               f"(no {FEATURES_OUTPUT} output or no trunk_head network)")
        cls, msk, feats = self.session.run(["class_logits", "mask_logits", FEATURES_OUTPUT],
                                           {"image": self.preprocess(rgb, "image")})
        return cls[0], msk[0], self._trunk_head().logits(feats)

    def trunk_map(self, rgb: np.ndarray, size: tuple[int, int] | None = None,
                  tile_frac: float | None = TRUNK_TILE_FRAC) -> np.ndarray:
        """Trunk probability ``(H, W)`` float32 of a photo at ``size`` (default the photo's): the
        trunk head's over square tiles of side ``tile_frac`` x the photo's long side, half a tile
        apart (:func:`tile_origins`), each at the network's input size, blended by
        :func:`tile_weight` (:data:`TRUNK_TILE_BLEND`); None: one pass
        over the whole photo. A 40 px trunk of a 600 px photo is 17 px at the 256 px input, 34 px
        in a half-side tile.

        Raises
        ------
        MonodbhError
            No trunk head for this segmenter.
        """
        return blend_tiles(rgb, lambda im: self.raw_with_trunk(im)[2], size, tile_frac)

    def predict(self, rgb: np.ndarray, size: tuple[int, int] | None = None,
                score_threshold: float = 0.5, overlap_threshold: float = 0.8,
                mask_threshold: float = 0.5, work_max_side: int | None = 640,
                trunk: bool = False) -> SegmentationResult:
        """Segment a photo.

        Parameters
        ----------
        rgb : (H, W, 3) uint8
        size : (W, H), optional
            Output resolution; default the photo's.
        score_threshold, overlap_threshold, mask_threshold, work_max_side
            See :func:`panoptic_merge`.
        trunk : bool
            Also give the trunk probability (``trunk_prob``; the network must have the trunk
            head, :attr:`has_trunk`).
        """
        size = size or (rgb.shape[1], rgb.shape[0])
        if trunk:
            cls, msk, tl = self.raw_with_trunk(rgb)
        else:
            cls, msk = self.raw(rgb)
        res = panoptic_merge(cls, msk, size, (self.tree_class,), score_threshold,
                             overlap_threshold, mask_threshold, work_max_side)
        pan = res["panoptic"]
        segs = res["segments"]
        trees = sorted((s for s in segs if s["isthing"]), key=lambda s: -s["score"] * s["mask_prob"])
        lut_inst = np.zeros(len(segs) + 1, np.uint16)
        lut_sem = np.full(len(segs) + 1, 255, np.uint8)
        for s in segs:
            lut_sem[s["id"]] = s["label"]
        for k, s in enumerate(trees):
            lut_inst[s["id"]] = k + 1
        scores = np.array([s["score"] * s["mask_prob"] for s in trees], np.float32)
        return SegmentationResult(instance=lut_inst[pan], semantic=lut_sem[pan], tree_scores=scores,
                                  classes=self.classes, tree_class=self.tree_class,
                                  trunk_prob=trunk_probability(tl, size) if trunk else None)
