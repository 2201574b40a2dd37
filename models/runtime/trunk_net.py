"""The trunk network at run time (network kind ``trunk_net``): a photo's trunk map.

EfficientNet-Lite0's ImageNet features and a decoder trained on the generator's stem label
(``models/modeling/trunk_net.py``, ``docs/decisions/trunk-head.md``) tell a tree's stem from its
crown, limbs and neighbours' foliage. It reads the photo itself, not the segmenter's features,
and runs only where a trunk map is asked for (``dbh reconstruct``'s point flags); the measuring
path never asks. Imported by ``monodbh.toolkit``'s pipeline and the evaluation commands;
imports numpy and the runtime's common and segmenter modules only.
"""
from __future__ import annotations

import os
from typing import Any

import numpy as np

from monodbh.models.runtime.common import OnnxPredictor
from monodbh.models.runtime.segmenter import TRUNK_TILE_FRAC, blend_tiles

__all__ = ["TrunkNet"]


class TrunkNet(OnnxPredictor):
    """Photo ``(H, W, 3)`` uint8 -> trunk logits and trunk maps (kind ``"trunk_net"``).

    Parameters
    ----------
    path : path, optional
        ONNX file; default the shipped ``models/trunk_net_int8.onnx``.
    threads, manifest, spin : as :class:`~monodbh.models.runtime.common.OnnxPredictor`.
    """

    kind = "trunk_net"

    def __init__(self, path: str | os.PathLike | None = None, threads: int = 2,
                 manifest: dict[str, Any] | None = None, *, spin: bool = False) -> None:
        super().__init__("trunk_net", path, threads, manifest, spin=spin)

    @property
    def threshold(self) -> float:
        """Trunk probability from which a pixel counts as trunk (the spec's ``trunk_threshold``)."""
        return float(self.spec.get("extra", {}).get("trunk_threshold", 0.5))

    def logits(self, rgb: np.ndarray) -> np.ndarray:
        """Photo or tile ``(H, W, 3)`` uint8 -> trunk logits ``(S / 4, S / 4)`` float32 of it
        stretched to the input side ``S``."""
        return self.run({"image": self.preprocess(rgb, "image")})["trunk_logits"][0, 0]

    def trunk_map(self, rgb: np.ndarray, size: tuple[int, int] | None = None,
                  tile_frac: float | None = TRUNK_TILE_FRAC) -> np.ndarray:
        """Trunk probability ``(H, W)`` float32 at ``size`` = (W, H) (default the photo's): over
        square tiles of side ``tile_frac`` x the photo's long side, half a tile apart, blended
        (:func:`~monodbh.models.runtime.segmenter.blend_tiles`); None: one pass. A 40 px trunk
        of a 600 px photo is 17 px at the 256 px input, 34 px in a half-side tile."""
        return blend_tiles(rgb, self.logits, size, tile_frac)
