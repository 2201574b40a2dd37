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
    """Output of :meth:`Segmenter.predict` (all masks at ``size`` = (W, H)).

    Attributes
    ----------
    tree_masks : (N, H, W) bool
        One mask per detected tree (non-overlapping), sorted by decreasing score.
    tree_scores : (N,) float32
        Class probability x mean mask probability inside the mask.
    stuff_masks : dict name -> (H, W) bool
        ``sky``, ``ground``, ``other_vegetation``, ``other`` (present classes only).
    semantic : (H, W) uint8
        Semantic id per pixel (0 sky, 1 ground, 2 other vegetation, 3 tree, 4 other;
        255 = unassigned).
    instance : (H, W) uint16
        0 = no tree, k = ``tree_masks[k - 1]``.
    classes : tuple of str
    """

    tree_masks: np.ndarray
    tree_scores: np.ndarray
    stuff_masks: dict[str, np.ndarray]
    semantic: np.ndarray
    instance: np.ndarray
    classes: tuple[str, ...] = field(default_factory=tuple)

    @property
    def size(self) -> tuple[int, int]:
        return (self.semantic.shape[1], self.semantic.shape[0])


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.clip(x, -50, 50)))


def _softmax(x: np.ndarray) -> np.ndarray:
    e = np.exp(x - x.max(-1, keepdims=True))
    return e / e.sum(-1, keepdims=True)


def panoptic_merge(class_logits: np.ndarray, mask_logits: np.ndarray, size: tuple[int, int],
                   thing_classes: tuple[int, ...] = (3,), score_threshold: float = 0.5,
                   overlap_threshold: float = 0.8, mask_threshold: float = 0.5,
                   max_pixels_per_chunk: int = 4_000_000) -> dict[str, Any]:
    """Mask2Former panoptic inference: greedy, non-overlapping segments.

    Parameters
    ----------
    class_logits : (Q, C + 1)
        Last class is "no object".
    mask_logits : (Q, h, w)
    size : (W, H)
        Output resolution; masks are bilinearly resized (logit space) before merging, one query
        at a time (memory ``O(H * W)`` even for 12 MP photos).
    thing_classes : tuple of int
        Classes whose queries become separate instances (tree); others merge per class.
    score_threshold : float
        Min class probability of a kept query (Mask2Former ``object_mask_threshold``, 0.8 there).
    overlap_threshold : float
        Min fraction of a query's own mask that survives the arg-max (Mask2Former default 0.8).

    Returns
    -------
    dict
        ``segments``: list of ``{"id", "label", "score", "isthing"}``; ``panoptic`` (H, W) int32
        segment id per pixel (0 = none).
    """
    W, H = size
    C1 = class_logits.shape[-1]
    probs = _softmax(class_logits.astype(np.float32))
    labels = probs.argmax(-1)
    scores = probs.max(-1)
    keep = np.nonzero((labels != C1 - 1) & (scores > score_threshold))[0]
    panoptic = np.zeros((H, W), np.int32)
    segments: list[dict[str, Any]] = []
    if keep.size == 0:
        return {"segments": segments, "panoptic": panoptic}

    def up(q: int) -> np.ndarray:
        m = mask_logits[q].astype(np.float32)
        if m.shape != (H, W):
            m = cv2.resize(m, (W, H), interpolation=cv2.INTER_LINEAR)
        return _sigmoid(m)

    # pass 1: arg-max of score * mask prob over kept queries
    best = np.zeros((H, W), np.float32)
    owner = np.full((H, W), -1, np.int32)
    orig_area = np.zeros(len(keep), np.int64)
    for j, q in enumerate(keep):
        p = up(q)
        orig_area[j] = int((p >= mask_threshold).sum())
        v = p * scores[q]
        upd = v > best
        best[upd] = v[upd]
        owner[upd] = j
    # pass 2: segments in query order
    stuff_ids: dict[int, int] = {}
    next_id = 1
    for j, q in enumerate(keep):
        lab = int(labels[q])
        isthing = lab in thing_classes
        own = owner == j
        area = int(own.sum())
        if area == 0 or orig_area[j] == 0:
            continue
        mask = own & (up(q) >= mask_threshold)
        n = int(mask.sum())
        if n == 0 or area / orig_area[j] < overlap_threshold:
            continue
        if not isthing and lab in stuff_ids:
            panoptic[mask] = stuff_ids[lab]
            continue
        panoptic[mask] = next_id
        if not isthing:
            stuff_ids[lab] = next_id
        segments.append({"id": next_id, "label": lab, "score": float(scores[q]), "isthing": isthing,
                         "query": int(q)})
        next_id += 1
    return {"segments": segments, "panoptic": panoptic}


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
                mask_threshold: float = 0.5) -> SegmentationResult:
        """Segment a photo.

        Parameters
        ----------
        rgb : (H, W, 3) uint8
        size : (W, H), optional
            Output resolution; default the photo's.
        score_threshold, overlap_threshold, mask_threshold : float
            See :func:`panoptic_merge`.
        """
        size = size or (rgb.shape[1], rgb.shape[0])
        cls, msk = self.raw(rgb)
        res = panoptic_merge(cls, msk, size, (self.tree_class,), score_threshold,
                             overlap_threshold, mask_threshold)
        pan = res["panoptic"]
        W, H = size
        semantic = np.full((H, W), 255, np.uint8)
        instance = np.zeros((H, W), np.uint16)
        trees = sorted((s for s in res["segments"] if s["isthing"]), key=lambda s: -s["score"])
        tree_masks = np.zeros((len(trees), H, W), bool)
        tree_scores = np.zeros(len(trees), np.float32)
        for k, s in enumerate(trees):
            m = pan == s["id"]
            tree_masks[k] = m
            instance[m] = k + 1
            semantic[m] = s["label"]
            prob = _sigmoid(cv2.resize(msk[s["query"]].astype(np.float32), (W, H)))[m]
            tree_scores[k] = s["score"] * (float(prob.mean()) if prob.size else 0.0)
        stuff: dict[str, np.ndarray] = {}
        for s in res["segments"]:
            if s["isthing"]:
                continue
            m = pan == s["id"]
            semantic[m] = s["label"]
            name = self.classes[s["label"]] if s["label"] < len(self.classes) else str(s["label"])
            stuff[name] = m
        return SegmentationResult(tree_masks, tree_scores, stuff, semantic, instance, self.classes)


def __getattr__(name: str) -> Any:  # lazy re-export of the GAN predictors
    if name in ("DepthPredictor", "TreePredictor"):
        from monodbh.models import runtime_gan

        return getattr(runtime_gan, name)
    raise AttributeError(name)
