"""The networks' onnxruntime runtime: one module per network, one name per network.

Imported by ``monodbh.toolkit`` (the measuring path), the CLI, and the networks' training and
export code (which cut their inputs with the same functions); imports only numpy, cv2,
onnxruntime and ``monodbh.calib.errors`` (no torch).

* ``segmenter``: :mod:`.segmenter`, :class:`Segmenter`, ``models/segmenter_int8.onnx``
* ``depth``: :mod:`.depth`, :class:`DepthPredictor`, ``models/depth_int8.onnx`` (CDEN architecture)
* ``tree``: :mod:`.tree`, :class:`TreePredictor`, ``models/tree_int8.onnx``
* ``stem_base``: :mod:`.stem_base`, :class:`StemBaseFinder`, ``models/stem_base_int8.onnx``; ``stem_base_net``:
  :class:`StemBaseNetFinder`, ``models/stem_base_net_int8.onnx`` (asked where the first sees no base)
* ``stem_edge``: :mod:`.stem_edge`, :class:`StemEdgeFinder`, ``models/stem_edge_int8.onnx``
* ``rope_verifier``: :mod:`.rope_verifier`, :class:`RopeVerifier`, ``models/rope_verifier_int8.onnx``
* ``rope_finder``: :mod:`.rope_finder`, :class:`RopeFinder`, ``models/rope_finder_int8.onnx``
* ``trunk_head``: :mod:`.trunk_head`, :class:`TrunkHead`, ``models/trunk_head_int8.onnx`` (reads
  the segmenter's ``mask_features``; run by :meth:`Segmenter.predict` ``trunk=True`` only)
* ``trunk_net``: :mod:`.trunk_net`, :class:`TrunkNet`, ``models/trunk_net_int8.onnx`` (the photo's
  trunk map for ``dbh reconstruct``; read instead of the trunk head where shipped)

:mod:`.common` holds the sessions, the manifest and the shared image helpers;
:mod:`.networks` loads all of them at once (:func:`load_networks`) with the error model measured
for them (:func:`fresh_error_model`).
"""
from monodbh.models.runtime.common import MANIFEST_PATH, MODELS_DIR, OnnxPredictor, load_manifest
from monodbh.models.runtime.depth import DepthPredictor
from monodbh.models.runtime.networks import ERROR_MODEL_KINDS, Networks, fresh_error_model, load_networks
from monodbh.models.runtime.rope_finder import RopeFinder, RopeFinderConfig
from monodbh.models.runtime.rope_verifier import RopeVerifier
from monodbh.models.runtime.segmenter import Segmenter, SegmentationResult
from monodbh.models.runtime.stem_base import BaseEstimate, StemBaseFinder, StemBaseNetFinder
from monodbh.models.runtime.stem_edge import EdgeEstimate, StemEdgeFinder
from monodbh.models.runtime.tree import TreePredictor
from monodbh.models.runtime.trunk_head import TrunkHead
from monodbh.models.runtime.trunk_net import TrunkNet

__all__ = ["MANIFEST_PATH", "MODELS_DIR", "OnnxPredictor", "load_manifest", "Segmenter", "SegmentationResult",
           "DepthPredictor", "TreePredictor", "StemBaseFinder", "StemBaseNetFinder", "BaseEstimate", "StemEdgeFinder", "EdgeEstimate", "RopeVerifier", "RopeFinder",
           "RopeFinderConfig", "TrunkHead", "TrunkNet", "ERROR_MODEL_KINDS", "Networks", "fresh_error_model", "load_networks"]
