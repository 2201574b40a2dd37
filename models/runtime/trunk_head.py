"""The segmenter's trunk head at run time (network kind ``trunk_head``): trunk logits from the
segmenter's mask features.

The head tells a tree's trunk from its crown and limbs (``docs/decisions/trunk-head.md``). It
reads the segmenter's ``mask_features`` output, so it runs only when a trunk map is asked for
(:meth:`monodbh.models.runtime.segmenter.Segmenter.predict` ``trunk=True``); the measuring path
never asks. Imported by ``monodbh.models.runtime.segmenter``; imports numpy and
``monodbh.models.runtime.common`` only.
"""
from __future__ import annotations

import os
from typing import Any

import numpy as np

from monodbh.models.runtime.common import OnnxPredictor

__all__ = ["TrunkHead"]


class TrunkHead(OnnxPredictor):
    """Mask features ``(1, D, h, w)`` -> trunk logits ``(h, w)`` (kind ``"trunk_head"``).

    Parameters
    ----------
    path : path, optional
        ONNX file; default the shipped ``models/trunk_head_int8.onnx``.
    threads, manifest, spin : as :class:`~monodbh.models.runtime.common.OnnxPredictor`.
    """

    kind = "trunk_head"

    def __init__(self, path: str | os.PathLike | None = None, threads: int = 2,
                 manifest: dict[str, Any] | None = None, *, spin: bool = False) -> None:
        super().__init__("trunk_head", path, threads, manifest, spin=spin)

    @property
    def threshold(self) -> float:
        """Trunk probability from which a pixel counts as trunk (the spec's ``trunk_threshold``)."""
        return float(self.spec.get("extra", {}).get("trunk_threshold", 0.5))

    def logits(self, mask_features: np.ndarray) -> np.ndarray:
        """``(1, D, h, w)`` float32 -> ``(h, w)`` float32 trunk logits.

        Raises
        ------
        ValueError
            Features of another shape than the head's input.
        """
        want = self.input_shape("mask_features")
        if tuple(mask_features.shape) != want:
            raise ValueError(f"{self.path}: expected mask features of shape {want}, got {tuple(mask_features.shape)}")
        return self.run({"mask_features": np.ascontiguousarray(mask_features, np.float32)})["trunk_logits"][0, 0]
