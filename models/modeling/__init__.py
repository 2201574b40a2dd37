"""Torch ``nn.Module``s of the networks (training-only; never imported by the runtime).

Use the registry: ``build(kind, size)`` returns a fresh model with ``.spec`` (its
:class:`~monodbh.models.modeling.registry.ModelSpec`); ``get_spec(kind, size)`` the I/O contract.
Kinds: ``"segmenter"`` (``segmenter.py``), ``"cden"`` (``cden.py``), ``"treenet"`` (``treenet.py``),
``"basenet"`` (``basenet.py``, the stem-base finder), ``"ropenet"`` (``ropenet.py``, the rope-band verifier),
``"ropeseg"`` (``ropeseg.py``, the mask-free rope finder).
"""
from monodbh.models.modeling.registry import (BUILDERS, KIND_MODULES, SIZES, SPECS, ModelSpec,
                                              Preprocess, TensorSpec, build, get_spec, kinds,
                                              register)

__all__ = ["BUILDERS", "KIND_MODULES", "SIZES", "SPECS", "ModelSpec", "Preprocess", "TensorSpec",
           "build", "get_spec", "kinds", "register"]
