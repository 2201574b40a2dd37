"""onnxruntime predictors used on the measuring path (numpy + cv2 + onnxruntime only; no torch).

* :func:`load_manifest` - ``models/manifest.json`` (written by ``dbh export --ship``).
* :class:`OnnxPredictor` - base: CPU session (2 intra-op threads, all graph optimisations), the
  model's I/O spec (read from the ONNX metadata key ``monodbh_spec``, falling back to the
  manifest entry), image preprocessing from the spec.
* :class:`Segmenter` - tree instances + stuff masks (Mask2Former-style panoptic merge,
  :func:`panoptic_merge`).
* ``DepthPredictor`` and ``TreePredictor`` (CDEN depth and tree-silhouette networks) live in
  ``monodbh.models.runtime_gan`` (written by the GAN networks' owner on top of
  :class:`OnnxPredictor`); they are re-exported here lazily (``from monodbh.models.runtime
  import DepthPredictor`` works once that module exists).

Specs are plain dicts here (``ModelSpec.to_dict()`` of ``monodbh.models.modeling.registry``,
which this module must not import): ``inputs``/``outputs`` lists of ``{name, shape, dtype}``,
``preprocess`` list of ``{input, color, scale, mean, std, resize, interpolation}``, ``classes``,
``extra``.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import onnxruntime as ort

try:
    from monodbh.calib.errors import MonodbhError
except ImportError:  # until monodbh.calib.errors exists
    class MonodbhError(Exception):
        """User-facing error (one line naming the file and the problem)."""

__all__ = ["MODELS_DIR", "MANIFEST_PATH", "SPEC_METADATA_KEY", "MonodbhError", "load_manifest",
           "OnnxPredictor", "Segmenter", "SegmentationResult", "panoptic_merge",
           "preprocess_image"]

MODELS_DIR = Path(__file__).resolve().parent
MANIFEST_PATH = MODELS_DIR / "manifest.json"
#: onnxruntime's intra-op threads spin between work items (its default); off: they sleep
ORT_SPIN = os.environ.get("MONODBH_ORT_SPIN", "0") == "1"
SPEC_METADATA_KEY = "monodbh_spec"  # same as monodbh.models.export.onnx_io.SPEC_METADATA_KEY

_INTERP = {"area": cv2.INTER_AREA, "linear": cv2.INTER_LINEAR, "nearest": cv2.INTER_NEAREST,
           "cubic": cv2.INTER_CUBIC}


def load_manifest(path: str | os.PathLike | None = None) -> dict[str, Any]:
    """Read ``models/manifest.json`` (``{"format": 1, "models": {kind: entry}}``).

    Returns ``{"format": 1, "models": {}}`` when no model has been shipped yet.
    """
    p = Path(path) if path is not None else MANIFEST_PATH
    if not p.exists():
        return {"format": 1, "models": {}}
    try:
        return json.loads(p.read_text())
    except (OSError, ValueError) as e:
        raise MonodbhError(f"{p}: cannot read model manifest ({e})") from None


def preprocess_image(rgb: np.ndarray, pre: dict[str, Any], shape: tuple[int, ...]) -> np.ndarray:
    """RGB uint8 ``(H, W, 3)`` -> float32 ``(1, 3, h, w)`` per a spec ``preprocess`` entry.

    ``shape`` is the input's ``(1, 3, h, w)``. Resize mode ``"stretch"`` (aspect not kept).
    """
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) RGB image, got shape {rgb.shape}")
    h, w = int(shape[2]), int(shape[3])
    if pre.get("resize", "stretch") != "stretch":
        raise ValueError(f"unsupported resize mode {pre.get('resize')!r}")
    img = rgb if pre.get("color", "RGB") == "RGB" else rgb[..., ::-1]
    if img.shape[:2] != (h, w):
        interp = _INTERP[pre.get("interpolation", "area")]
        if img.shape[0] < h or img.shape[1] < w:
            interp = cv2.INTER_LINEAR
        img = cv2.resize(img, (w, h), interpolation=interp)
    x = img.astype(np.float32) * np.float32(pre.get("scale", 1 / 255))
    x = (x - np.asarray(pre["mean"], np.float32)) / np.asarray(pre["std"], np.float32)
    return np.ascontiguousarray(x.transpose(2, 0, 1)[None])


class OnnxPredictor:
    """Base class of the runtime predictors.

    Parameters
    ----------
    kind : str
        Model kind (``"segmenter"``, ``"cden"``, ``"treenet"``).
    path : path, optional
        ONNX file; default ``models/{kind}_int8.onnx`` as listed in the manifest.
    threads : int
        onnxruntime intra-op threads (2 = the laptop budget).

    Attributes
    ----------
    session : onnxruntime.InferenceSession
    spec : dict
        ``ModelSpec.to_dict()`` of the model.
    path : Path
    """

    kind: str = ""

    def __init__(self, kind: str | None = None, path: str | os.PathLike | None = None,
                 threads: int = 2, manifest: dict[str, Any] | None = None) -> None:
        self.kind = kind or self.kind
        entry: dict[str, Any] = {}
        if path is None:
            man = manifest if manifest is not None else load_manifest()
            entry = man.get("models", {}).get(self.kind, {})
            if not entry:
                raise MonodbhError(f"{MANIFEST_PATH}: no shipped '{self.kind}' model "
                                   f"(run `dbh export RUN_DIR --ship`)")
            path = MODELS_DIR / entry["file"]
        self.path = Path(path)
        if not self.path.exists():
            raise MonodbhError(f"{self.path}: model file not found")
        so = ort.SessionOptions()
        so.intra_op_num_threads = threads
        so.inter_op_num_threads = 1
        so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        so.log_severity_level = 3
        if not ORT_SPIN:
            # idle pool threads sleep instead of spinning: the pipeline runs the depth network
            # beside the rope search, and spinning threads take the rope search's core
            so.add_session_config_entry("session.intra_op.allow_spinning", "0")
        try:
            self.session = ort.InferenceSession(str(self.path), so,
                                                providers=["CPUExecutionProvider"])
        except Exception as e:  # noqa: BLE001 - onnxruntime raises several types
            raise MonodbhError(f"{self.path}: cannot load ONNX model ({e})") from None
        meta = self.session.get_modelmeta().custom_metadata_map
        if SPEC_METADATA_KEY in meta:
            self.spec = json.loads(meta[SPEC_METADATA_KEY])
        elif "spec" in entry:
            self.spec = entry["spec"]
        else:
            raise MonodbhError(f"{self.path}: no I/O spec in the model metadata or manifest")
        if self.kind and self.spec.get("kind") != self.kind:
            raise MonodbhError(f"{self.path}: is a '{self.spec.get('kind')}' model, "
                               f"expected '{self.kind}'")
        self.input_names = [t["name"] for t in self.spec["inputs"]]
        self.output_names = [t["name"] for t in self.spec["outputs"]]

    def input_shape(self, name: str) -> tuple[int, ...]:
        for t in self.spec["inputs"]:
            if t["name"] == name:
                return tuple(t["shape"])
        raise KeyError(name)

    def preprocess(self, rgb: np.ndarray, input_name: str = "image") -> np.ndarray:
        """Photo -> network input per the spec's preprocess entry for ``input_name``."""
        pre = next((p for p in self.spec.get("preprocess", []) if p["input"] == input_name), None)
        if pre is None:
            raise KeyError(f"no preprocessing declared for input {input_name!r}")
        return preprocess_image(rgb, pre, self.input_shape(input_name))

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Raw run: ``{input: array}`` -> ``{output: array}``."""
        return dict(zip(self.output_names, self.session.run(self.output_names, feeds)))


# --------------------------------------------------------------------------- segmentation


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

    ``tree_masks`` (N, H, W) bool and ``stuff_masks`` (name -> (H, W) bool) are derived on
    demand (a 12 MP photo with 40 trees would need 480 MB of masks).
    """

    instance: np.ndarray
    semantic: np.ndarray
    tree_scores: np.ndarray
    classes: tuple[str, ...] = field(default_factory=tuple)
    tree_class: int = 3

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
    if work_max_side and max(W, H) > work_max_side:
        f = work_max_side / max(W, H)
        w, h = max(1, int(round(W * f))), max(1, int(round(H * f)))
    else:
        w, h = W, H
    C1 = class_logits.shape[-1]
    probs = _softmax(class_logits.astype(np.float32))
    labels = probs.argmax(-1)
    scores = probs.max(-1)
    keep = np.nonzero((labels != C1 - 1) & (scores > score_threshold))[0]
    segments: list[dict[str, Any]] = []
    if keep.size == 0:
        return {"segments": segments, "panoptic": np.zeros((H, W), np.int32)}
    # one pass over kept queries: arg-max of score * prob, the owner's prob, each query's area
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
    valid = (owner >= 0) & (best_p >= mask_threshold)
    own_area = np.bincount(owner[owner >= 0], minlength=len(keep))
    final_area = np.bincount(owner[valid], minlength=len(keep))
    prob_sum = np.bincount(owner[valid], weights=best_p[valid], minlength=len(keep))
    lut = np.zeros(len(keep) + 1, np.int32)  # index j + 1 -> segment id (index 0: owner -1)
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
    pan = np.where(valid, lut[owner + 1], 0).astype(np.int32)
    if (w, h) != (W, H):
        pan = cv2.resize(pan, (W, H), interpolation=cv2.INTER_NEAREST)
    return {"segments": segments, "panoptic": pan}


class Segmenter(OnnxPredictor):
    """Tree instance + stuff segmentation (Mask2Former-style network, kind ``"segmenter"``).

    Outputs of the network: ``class_logits`` (1, Q, C + 1), ``mask_logits`` (1, Q, h, w).
    """

    kind = "segmenter"

    def __init__(self, path: str | os.PathLike | None = None, threads: int = 2,
                 manifest: dict[str, Any] | None = None) -> None:
        super().__init__("segmenter", path, threads, manifest)
        self.classes = tuple(self.spec.get("classes") or ())
        self.tree_class = int(self.spec.get("extra", {}).get("tree_class", 3))

    def raw(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Network outputs for a photo: ``(class_logits (Q, C+1), mask_logits (Q, h, w))``."""
        out = self.run({"image": self.preprocess(rgb, "image")})
        return out["class_logits"][0], out["mask_logits"][0]

    def predict(self, rgb: np.ndarray, size: tuple[int, int] | None = None,
                score_threshold: float = 0.5, overlap_threshold: float = 0.8,
                mask_threshold: float = 0.5, work_max_side: int | None = 640
                ) -> SegmentationResult:
        """Segment a photo.

        Parameters
        ----------
        rgb : (H, W, 3) uint8
        size : (W, H), optional
            Output resolution; default the photo's.
        score_threshold, overlap_threshold, mask_threshold, work_max_side
            See :func:`panoptic_merge`.
        """
        size = size or (rgb.shape[1], rgb.shape[0])
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
                                  classes=self.classes, tree_class=self.tree_class)


def __getattr__(name: str) -> Any:  # lazy re-export of the GAN predictors
    if name in ("DepthPredictor", "TreePredictor"):
        from monodbh.models import runtime_gan

        return getattr(runtime_gan, name)
    raise AttributeError(name)
