"""Torch ``nn.Module``s of the networks (training-only; never imported by the runtime).

Use the registry: ``build(kind, size)`` returns a fresh model with ``.spec`` (its
:class:`~monodbh.models.modeling.registry.ModelSpec`); ``get_spec(kind, size)`` the I/O contract.
Kinds: ``"segmenter"`` (``segmenter.py``), ``"depth"`` (``cden.py``, the CDEN architecture), ``"tree"``
(``tree.py``), ``"stem_base"`` (``stem_base.py``, the stem-base finder), ``"rope_verifier"``
(``rope_verifier.py``, the rope-band verifier), ``"rope_finder"`` (``rope_finder.py``, the mask-free rope finder).
"""
from monodbh.models.modeling.registry import (BUILDERS, KIND_MODULES, SIZES, SPECS, ModelSpec,
                                              Preprocess, TensorSpec, build, get_spec, kinds,
                                              register)

__all__ = ["BUILDERS", "KIND_MODULES", "SIZES", "SPECS", "ModelSpec", "Preprocess", "TensorSpec",
           "build", "get_spec", "kinds", "register"]
