"""Registry of network kinds and their I/O contracts (the single source of truth).

Every trainable network kind (``"segmenter"``, ``"depth"``, ``"tree"``) registers

* a **builder** ``builder(size) -> nn.Module`` (sizes ``"tiny"`` for tests, ``"base"`` for shipping);
* a **spec** ``spec(size) -> ModelSpec``: ONNX input/output names and shapes, preprocessing
  constants, class list / output mapping, and the task metric used to accept an int8 model.

Export (``monodbh.models.export``) and the runtime (``monodbh.models.runtime``) both use the spec:
export embeds ``ModelSpec.to_dict()`` as JSON into the ONNX file's metadata (key ``monodbh_spec``)
and into ``models/manifest.json``; the runtime reads it back from there. The runtime never imports
this module (it only sees the serialised dict), so this file is torch-free at import time.

Adding a kind (e.g. in ``modeling/cden.py``)::

    from monodbh.models.modeling.registry import register, ModelSpec, TensorSpec, Preprocess

    def cden_spec(size: str) -> ModelSpec: ...

    @register("depth", spec=cden_spec)
    def build_cden(size: str) -> nn.Module: ...

and add ``"depth": "monodbh.models.modeling.cden"`` to :data:`KIND_MODULES` (already done for the
three planned kinds) so that ``build("depth", "tiny")`` imports the module on demand.

Conventions
-----------
* Shapes are fixed (batch 1) in the exported graph: ``TensorSpec.shape`` is a tuple of ints,
  ``(1, C, H, W)`` for images.
* Image preprocessing (``Preprocess``): RGB uint8 ``(H, W, 3)`` -> resize (``resize``: ``"stretch"``
  = plain resize to the input's ``(H, W)``, aspect ratio not kept) -> float32 ``/ 255`` ->
  ``(x - mean) / std`` per channel -> ``(1, 3, H, W)``.
"""
from __future__ import annotations

import importlib
import json
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any, Callable

if TYPE_CHECKING:  # pragma: no cover
    from torch import nn

__all__ = [
    "IMAGENET_MEAN", "IMAGENET_STD", "SIZES", "TensorSpec", "Preprocess", "ModelSpec",
    "BUILDERS", "SPECS", "KIND_MODULES", "register", "build", "get_spec", "kinds",
]

IMAGENET_MEAN: tuple[float, float, float] = (0.485, 0.456, 0.406)
IMAGENET_STD: tuple[float, float, float] = (0.229, 0.224, 0.225)
SIZES: tuple[str, ...] = ("tiny", "base", "wide", "base384", "effl0")  # "wide": depth/tree/rope_finder; "base384", "effl0": segmenter only


@dataclass(frozen=True)
class TensorSpec:
    """One ONNX graph input or output.

    Parameters
    ----------
    name : str
        Graph name (e.g. ``"image"``).
    shape : tuple of int
        Fixed shape, batch first (e.g. ``(1, 3, 256, 256)``).
    dtype : str
        numpy dtype name, ``"float32"`` unless stated.
    description : str
        Free text (units, value range), copied into the manifest.
    """

    name: str
    shape: tuple[int, ...]
    dtype: str = "float32"
    description: str = ""


@dataclass(frozen=True)
class Preprocess:
    """How an RGB uint8 photo becomes an image input (see module docstring).

    ``input`` names the graph input it feeds. ``mean``/``std`` apply after scaling by ``scale``.
    Non-image inputs (e.g. a mask channel) are documented by the kind in ``ModelSpec.extra``.
    """

    input: str = "image"
    color: str = "RGB"
    scale: float = 1.0 / 255.0
    mean: tuple[float, ...] = IMAGENET_MEAN
    std: tuple[float, ...] = IMAGENET_STD
    resize: str = "stretch"
    interpolation: str = "area"


@dataclass(frozen=True)
class ModelSpec:
    """I/O contract of one network kind at one size.

    Parameters
    ----------
    kind, size : str
        Registry key and size name.
    inputs, outputs : tuple of TensorSpec
        Graph inputs/outputs in order (the torch module's ``forward`` takes the inputs
        positionally in this order and returns a tensor or a tuple in the outputs' order when
        in ``eval()`` mode).
    preprocess : tuple of Preprocess
        Photo -> input recipe for each image input.
    classes : tuple of str or None
        Class names by index (segmenter: index == semantic id of the synthetic data).
    metric : str
        Key of the task metric (returned by the kind's eval hook) used to accept an int8 model.
    higher_is_better : bool
        Direction of ``metric``.
    extra : dict
        Kind-specific JSON-serialisable constants (e.g. depth mapping, no-object index).
    opset : int
        ONNX opset used for export.
    """

    kind: str
    size: str
    inputs: tuple[TensorSpec, ...]
    outputs: tuple[TensorSpec, ...]
    preprocess: tuple[Preprocess, ...] = (Preprocess(),)
    classes: tuple[str, ...] | None = None
    metric: str = "score"
    higher_is_better: bool = True
    extra: dict[str, Any] = field(default_factory=dict)
    opset: int = 17

    @property
    def input_names(self) -> list[str]:
        return [t.name for t in self.inputs]

    @property
    def output_names(self) -> list[str]:
        return [t.name for t in self.outputs]

    def input(self, name: str) -> TensorSpec:
        """Return the input called ``name``."""
        for t in self.inputs:
            if t.name == name:
                return t
        raise KeyError(name)

    def output(self, name: str) -> TensorSpec:
        """Return the output called ``name``."""
        for t in self.outputs:
            if t.name == name:
                return t
        raise KeyError(name)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable dict (lists instead of tuples); inverse of :meth:`from_dict`."""
        return json.loads(json.dumps(asdict(self)))

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "ModelSpec":
        """Rebuild a spec from :meth:`to_dict` output."""
        return cls(
            kind=d["kind"], size=d["size"],
            inputs=tuple(TensorSpec(t["name"], tuple(t["shape"]), t.get("dtype", "float32"),
                                    t.get("description", "")) for t in d["inputs"]),
            outputs=tuple(TensorSpec(t["name"], tuple(t["shape"]), t.get("dtype", "float32"),
                                     t.get("description", "")) for t in d["outputs"]),
            preprocess=tuple(Preprocess(**{**p, "mean": tuple(p["mean"]), "std": tuple(p["std"])})
                             for p in d.get("preprocess", [])),
            classes=tuple(d["classes"]) if d.get("classes") is not None else None,
            metric=d.get("metric", "score"), higher_is_better=d.get("higher_is_better", True),
            extra=dict(d.get("extra", {})), opset=d.get("opset", 17),
        )


BUILDERS: dict[str, Callable[[str], "nn.Module"]] = {}
SPECS: dict[str, Callable[[str], ModelSpec]] = {}

#: kind -> module that registers it (imported lazily by :func:`build` / :func:`get_spec`).
KIND_MODULES: dict[str, str] = {
    "segmenter": "monodbh.models.modeling.segmenter",
    "depth": "monodbh.models.modeling.cden",
    "tree": "monodbh.models.modeling.tree",
    "stem_base": "monodbh.models.modeling.stem_base",
    "stem_edge": "monodbh.models.modeling.stem_edge",
    "rope_verifier": "monodbh.models.modeling.rope_verifier",
    "rope_finder": "monodbh.models.modeling.rope_finder",
}


def register(kind: str, spec: Callable[[str], ModelSpec]) -> Callable:
    """Decorator registering ``builder(size) -> nn.Module`` and its ``spec(size)`` under ``kind``.

    The built module gets attributes ``spec`` (its :class:`ModelSpec`), ``kind`` and ``size``.
    """

    def deco(builder: Callable[[str], "nn.Module"]) -> Callable[[str], "nn.Module"]:
        BUILDERS[kind] = builder
        SPECS[kind] = spec
        return builder

    return deco


def _ensure(kind: str) -> None:
    if kind in BUILDERS:
        return
    mod = KIND_MODULES.get(kind)
    if mod is None:
        raise KeyError(f"unknown model kind {kind!r}; known: {sorted(set(KIND_MODULES) | set(BUILDERS))}")
    importlib.import_module(mod)
    if kind not in BUILDERS:
        raise KeyError(f"module {mod} did not register kind {kind!r}")


def kinds() -> list[str]:
    """All known kind names (registered or importable)."""
    return sorted(set(KIND_MODULES) | set(BUILDERS))


def get_spec(kind: str, size: str = "base") -> ModelSpec:
    """Return the :class:`ModelSpec` of ``kind`` at ``size``."""
    if size not in SIZES:
        raise ValueError(f"size must be one of {SIZES}, got {size!r}")
    _ensure(kind)
    return SPECS[kind](size)


def build(kind: str, size: str = "base") -> "nn.Module":
    """Build a fresh (randomly initialised) model of ``kind`` at ``size`` with ``.spec`` attached."""
    spec = get_spec(kind, size)
    model = BUILDERS[kind](size)
    model.spec = spec
    model.kind = kind
    model.size = size
    return model
