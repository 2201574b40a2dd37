"""What every network's runtime shares: onnxruntime sessions, the model manifest, uint8 images in
and out, and the affine patch geometry of the stem-base and rope-verifier networks.

Imported by the per-network modules of ``monodbh.models.runtime`` and by the networks' training
code (so that training cuts its inputs exactly as the runtime does); imports only numpy, cv2,
onnxruntime and ``monodbh.calib.errors`` (no torch: this is on the measuring path).

The manifest (:func:`load_manifest`, ``models/manifest.json``, written by ``dbh export --ship``)
lists each shipped network by its kind (``segmenter``, ``depth``, ``tree``, ``stem_base``,
``rope_verifier``, ``rope_finder``) and the error model measured for them. A manifest or an ONNX
file written before the networks had these names (kinds ``cden``, ``treenet``, ``basenet``,
``ropenet``, ``ropeseg``) is read under today's names (:data:`LEGACY_KINDS`): the shipped ONNX
files keep their old kind in their metadata, since their sha256 is what the error model was
measured for.

Specs are plain dicts here (``ModelSpec.to_dict()`` of ``monodbh.models.modeling.registry``,
which this package must not import): ``inputs``/``outputs`` lists of ``{name, shape, dtype}``,
``preprocess`` list of ``{input, color, scale, mean, std, resize, interpolation}``, ``classes``,
``extra``.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import onnxruntime as ort

from monodbh.calib.errors import MonodbhError

__all__ = ["MODELS_DIR", "MANIFEST_PATH", "SPEC_METADATA_KEY", "LEGACY_KINDS", "IMAGENET_MEAN",
           "IMAGENET_STD", "MEAN_RGB", "MEAN_RGB_U8", "MonodbhError", "canonical_kind", "load_manifest",
           "session_options", "OnnxPredictor", "normalize_rgb", "preprocess_image", "to_uint8",
           "stack_feed", "affine_region", "affine_inside", "affine_patch"]

#: folder of the shipped ``*.onnx`` files and ``manifest.json`` (the ``monodbh.models`` package)
MODELS_DIR = Path(__file__).resolve().parent.parent
MANIFEST_PATH = MODELS_DIR / "manifest.json"
SPEC_METADATA_KEY = "monodbh_spec"  # same as monodbh.models.export.onnx_io.SPEC_METADATA_KEY
#: network kinds before the networks were renamed -> today's kinds (read once, at load)
LEGACY_KINDS: dict[str, str] = {"cden": "depth", "treenet": "tree", "basenet": "stem_base",
                                "ropenet": "rope_verifier", "ropeseg": "rope_finder"}

#: ImageNet normalisation of every network's RGB input (structural: the networks were trained so)
IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)
#: the mean colour in 0-255 (float): what the networks see outside the photo
MEAN_RGB: tuple[float, float, float] = tuple(float(v) for v in IMAGENET_MEAN * 255.0)
#: :data:`MEAN_RGB` rounded to uint8
MEAN_RGB_U8 = np.round(IMAGENET_MEAN * 255).astype(np.uint8)

_INTERP = {"area": cv2.INTER_AREA, "linear": cv2.INTER_LINEAR, "nearest": cv2.INTER_NEAREST,
           "cubic": cv2.INTER_CUBIC}


# --------------------------------------------------------------------------- manifest


def canonical_kind(kind: str | None) -> str | None:
    """Today's name of a network kind (``"cden"`` -> ``"depth"``, see :data:`LEGACY_KINDS`).

    Examples
    --------
    >>> canonical_kind("basenet"), canonical_kind("stem_base"), canonical_kind("segmenter")
    ('stem_base', 'stem_base', 'segmenter')
    """
    return LEGACY_KINDS.get(kind, kind) if kind is not None else None


def _rename_kinds(table: dict[str, Any], path: Path) -> None:
    """Rename the legacy kinds among ``table``'s keys in place (refused when both names are there)."""
    for old, new in LEGACY_KINDS.items():
        if old not in table:
            continue
        if new in table:
            raise MonodbhError(f"{path}: lists the '{new}' network twice (also under its old name "
                               f"'{old}'): remove one")
        table[new] = table.pop(old)


def _upgrade_kinds(manifest: dict[str, Any], path: Path) -> dict[str, Any]:
    """A manifest written under the old kinds, under today's (models, their specs, the error model's
    ``models``); the ``file`` fields are kept (they name the files as they are on disk)."""
    models = manifest.get("models")
    if isinstance(models, dict):
        _rename_kinds(models, path)
        for entry in models.values():
            spec = entry.get("spec") if isinstance(entry, dict) else None
            if isinstance(spec, dict) and "kind" in spec:
                spec["kind"] = canonical_kind(spec["kind"])
    em_models = (manifest.get("error_model") or {}).get("models")
    if isinstance(em_models, dict):
        _rename_kinds(em_models, path)
    return manifest


def load_manifest(path: str | os.PathLike | None = None) -> dict[str, Any]:
    """Read ``models/manifest.json`` (``{"format": 1, "models": {kind: entry}, "error_model": ...}``).

    Returns ``{"format": 1, "models": {}}`` when no model has been shipped yet. A manifest of the
    old kinds comes back under today's (see the module docstring).
    """
    p = Path(path) if path is not None else MANIFEST_PATH
    if not p.exists():
        return {"format": 1, "models": {}}
    try:
        manifest = json.loads(p.read_text())
    except (OSError, ValueError) as e:
        raise MonodbhError(f"{p}: cannot read model manifest ({e})") from None
    if not isinstance(manifest, dict):
        raise MonodbhError(f"{p}: not a model manifest (expected a JSON object)")
    return _upgrade_kinds(manifest, p)


# --------------------------------------------------------------------------- sessions


def session_options(threads: int = 2, *, spin: bool = False) -> ort.SessionOptions:
    """CPU session options of every network: ``threads`` intra-op threads, one inter-op thread,
    sequential execution, all graph optimisations.

    Parameters
    ----------
    threads : int
        onnxruntime intra-op threads (2: the laptop budget, see ``docs/decisions/threads.md``).
    spin : bool
        Idle intra-op threads spin between work items (onnxruntime's default) instead of
        sleeping; off because the depth network runs beside the rope search, whose core spinning
        threads would take (``docs/decisions/threads.md``).
    """
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.log_severity_level = 3
    if not spin:
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return so


class OnnxPredictor:
    """Base class of the network predictors: an onnxruntime session and the network's I/O spec.

    Parameters
    ----------
    kind : str
        Network kind (``"segmenter"``, ``"depth"``, ``"tree"``, ``"stem_base"``,
        ``"rope_verifier"``, ``"rope_finder"``).
    path : path, optional
        ONNX file; default the one the manifest lists for ``kind`` (``models/{kind}_int8.onnx``).
    threads : int
        onnxruntime intra-op threads (:func:`session_options`).
    manifest : dict, optional
        Manifest to look the shipped model up in when ``path`` is None (default
        ``models/manifest.json``).
    spin : bool
        See :func:`session_options`.

    Attributes
    ----------
    session : onnxruntime.InferenceSession
    spec : dict
        ``ModelSpec.to_dict()`` of the model (read from the ONNX metadata key
        :data:`SPEC_METADATA_KEY`, else the manifest entry); ``spec["kind"]`` under today's name.
    path : Path
    """

    kind: str = ""

    def __init__(self, kind: str | None = None, path: str | os.PathLike | None = None,
                 threads: int = 2, manifest: dict[str, Any] | None = None, *, spin: bool = False) -> None:
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
        try:
            self.session = ort.InferenceSession(str(self.path), session_options(threads, spin=spin),
                                                providers=["CPUExecutionProvider"])
        except Exception as e:  # noqa: BLE001 - onnxruntime raises several types
            raise MonodbhError(f"{self.path}: cannot load ONNX model ({e})") from None
        meta = self.session.get_modelmeta().custom_metadata_map
        if SPEC_METADATA_KEY in meta:
            spec = json.loads(meta[SPEC_METADATA_KEY])
        elif "spec" in entry:
            spec = dict(entry["spec"])
        else:
            raise MonodbhError(f"{self.path}: no I/O spec in the model metadata or manifest")
        spec["kind"] = canonical_kind(spec.get("kind"))
        self.spec = spec
        if self.kind and self.spec.get("kind") != self.kind:
            raise MonodbhError(f"{self.path}: is a '{self.spec.get('kind')}' model, "
                               f"expected '{self.kind}'")
        self.input_names = [t["name"] for t in self.spec["inputs"]]
        self.output_names = [t["name"] for t in self.spec["outputs"]]

    def input_shape(self, name: str) -> tuple[int, ...]:
        """Shape of input ``name`` per the spec, e.g. ``(1, 3, 256, 256)``."""
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


# --------------------------------------------------------------------------- uint8 images in and out


def normalize_rgb(rgb: np.ndarray, mean: np.ndarray = IMAGENET_MEAN,
                  std: np.ndarray = IMAGENET_STD) -> np.ndarray:
    """``(H, W, 3)`` uint8 -> ``(3, H, W)`` float32, ``(x / 255 - mean) / std``."""
    x = rgb.astype(np.float32) * (1.0 / 255.0)
    x = (x - np.asarray(mean, np.float32)) / np.asarray(std, np.float32)
    return np.ascontiguousarray(x.transpose(2, 0, 1))


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


def to_uint8(x: np.ndarray) -> np.ndarray:
    """Resampled float pixels (any shape) -> uint8, rounded half up and clipped to 0-255."""
    return np.clip(x + 0.5, 0, 255).astype(np.uint8)


def stack_feed(rgb: np.ndarray, *flags: np.ndarray) -> np.ndarray:
    """``(h, w, 3)`` uint8 and ``(h, w)`` bool flags -> ``(3 + len(flags), h, w)`` float32: the
    normalised RGB (:func:`normalize_rgb`) followed by the flags as 0/1 planes."""
    return np.ascontiguousarray(np.concatenate(
        [normalize_rgb(rgb)] + [f[None].astype(np.float32) for f in flags], 0))


# --------------------------------------------------------------------------- affine patches


def affine_region(A: np.ndarray, out_w: int, out_h: int, scale_px: float, width: int,
                  height: int) -> tuple[int, int, int, int]:
    """The part ``(x0, y0, x1, y1)`` of a ``width x height`` photo that an ``out_w x out_h``
    patch touches, padded for the anti-aliasing blur and bilinear sampling; clipped to the photo
    (empty when ``x1 <= x0`` or ``y1 <= y0``).

    Parameters
    ----------
    A : (2, 3)
        Affine map from patch pixel ``(col, row)`` to photo pixel ``(x, y)``.
    out_w, out_h : int
        Patch size.
    scale_px : float
        Photo pixels per patch pixel (the larger axis's): the padding is ``ceil(2 max(scale, 1)) + 2``.
    width, height : int
        Photo size.
    """
    corners = np.array([[0, 0, 1], [out_w, 0, 1], [0, out_h, 1], [out_w, out_h, 1]], float) @ A.T
    pad = int(math.ceil(2 * max(scale_px, 1.0))) + 2
    x0 = max(int(math.floor(corners[:, 0].min())) - pad, 0)
    y0 = max(int(math.floor(corners[:, 1].min())) - pad, 0)
    x1 = min(int(math.ceil(corners[:, 0].max())) + pad, width)
    y1 = min(int(math.ceil(corners[:, 1].max())) + pad, height)
    return x0, y0, x1, y1


def affine_inside(A: np.ndarray, out_w: int, out_h: int, width: int, height: int) -> np.ndarray:
    """``(out_h, out_w)`` bool: the patch pixels whose centre (``A @ (col, row, 1)``) lies inside
    a ``width x height`` photo (pixel centres at integers)."""
    cols, rows = np.meshgrid(np.arange(out_w) + 0.0, np.arange(out_h) + 0.0)
    px = A[0, 0] * cols + A[0, 1] * rows + A[0, 2]
    py = A[1, 0] * cols + A[1, 1] * rows + A[1, 2]
    return (px >= 0) & (px <= width - 1) & (py >= 0) & (py <= height - 1)


def affine_patch(rgb: np.ndarray, A: np.ndarray, out_w: int, out_h: int, sx: float,
                 sy: float) -> tuple[np.ndarray, np.ndarray]:
    """Resample an ``out_h x out_w`` patch of the photo through the affine map ``A``.

    Parameters
    ----------
    rgb : (H, W, 3) uint8 photo.
    A : (2, 3) affine map from patch pixel ``(col, row)`` to photo pixel ``(x, y)``.
    out_w, out_h : patch size.
    sx, sy : photo pixels per patch column / row (where above 1.25, the photo is blurred first,
        each axis by its own factor, so that the shrink does not alias).

    Returns
    -------
    (patch, inside): ``(out_h, out_w, 3)`` uint8 (outside the photo: :data:`MEAN_RGB_U8`) and
    ``(out_h, out_w)`` bool, True where the patch lies inside the photo.
    """
    H, W = rgb.shape[:2]
    shrink = max(sx, sy)
    x0, y0, x1, y1 = affine_region(A, out_w, out_h, shrink, W, H)
    inside = np.zeros((out_h, out_w), bool)
    if x1 <= x0 or y1 <= y0:
        out = np.empty((out_h, out_w, 3), np.uint8)
        out[...] = MEAN_RGB_U8
        return out, inside
    roi = rgb[y0:y1, x0:x1].astype(np.float32)
    if shrink > 1.25:      # anti-alias before shrinking (each axis by its own factor)
        sgx, sgy = 0.5 * math.sqrt(max(sx * sx - 1.0, 0.0)), 0.5 * math.sqrt(max(sy * sy - 1.0, 0.0))
        roi = cv2.GaussianBlur(roi, (0, 0), sigmaX=max(sgx, 0.01), sigmaY=max(sgy, 0.01),
                               borderType=cv2.BORDER_REPLICATE)
    Ar = A.copy()
    Ar[:, 2] -= (x0, y0)
    # warpAffine maps destination -> source with WARP_INVERSE_MAP
    out = cv2.warpAffine(roi, Ar, (out_w, out_h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=MEAN_RGB)
    inside = affine_inside(A, out_w, out_h, W, H)
    out = to_uint8(out)
    out[~inside] = MEAN_RGB_U8
    return out, inside
