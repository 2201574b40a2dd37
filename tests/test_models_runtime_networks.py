"""Loading the shipped networks together, and the error model measured for exactly them."""
import hashlib
import json

import pytest

from monodbh.calib.errors import MonodbhError
from monodbh.models.runtime import (ERROR_MODEL_KINDS, MANIFEST_PATH, MODELS_DIR, DepthPredictor, RopeFinder,
                                    RopeVerifier, Segmenter, StemBaseFinder, TreePredictor, fresh_error_model,
                                    load_manifest, load_networks)
from monodbh.models.runtime.common import LEGACY_KINDS

SHIPPED = ("segmenter", "depth", "tree", "stem_base", "stem_base_net", "stem_edge", "rope_verifier", "rope_finder", "trunk_head",
           "trunk_net")


def _sha256(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_shipped_files_carry_one_name_per_network():
    man = load_manifest()
    assert set(man["models"]) == set(SHIPPED)
    for kind, entry in man["models"].items():
        assert entry["file"] == f"{kind}_int8.onnx" and entry["spec"]["kind"] == kind
        assert _sha256(MODELS_DIR / entry["file"]) == entry["sha256"]


def test_shipped_error_model_is_fresh_for_the_shipped_files():
    """The error model was measured for exactly these files: if it is not recognised, every sigma
    falls back to the built-in defaults."""
    man = load_manifest()
    em = fresh_error_model(man)
    assert em and em["sigma"] and em["rank"] and em["distance_calibration"]
    assert set(em["models"]) == set(ERROR_MODEL_KINDS)
    assert em["models"] == {k: _sha256(MODELS_DIR / f"{k}_int8.onnx") for k in ERROR_MODEL_KINDS}
    # measured with mirror-image averaging of the depth network: stale when run without
    assert fresh_error_model(man, depth_flip_tta=False) == {}
    # stale once one of its networks changes
    man["models"]["tree"]["sha256"] = "0" * 64
    assert fresh_error_model(man) == {}


def test_load_networks_shipped():
    nets = load_networks(threads=1, stem_base_threshold=0.4)
    assert isinstance(nets.segmenter, Segmenter) and isinstance(nets.depth, DepthPredictor)
    assert isinstance(nets.tree, TreePredictor) and isinstance(nets.stem_base, StemBaseFinder)
    assert isinstance(nets.rope_verifier, RopeVerifier) and isinstance(nets.rope_finder, RopeFinder)
    assert nets.models_dir == MODELS_DIR and nets.stem_base.threshold == 0.4 and nets.depth.flip_tta
    em = load_manifest()["error_model"]
    assert not nets.error_model_stale
    assert nets.sigma == em["sigma"] and nets.rank == em["rank"]
    assert nets.distance_calibration == em["distance_calibration"]
    stale = load_networks(threads=1, depth_flip_tta=False)
    assert stale.error_model_stale and stale.sigma is None and not stale.depth.flip_tta


def _copy_models(dst, kinds=SHIPPED, rename=lambda k: k):
    """The shipped manifest and files in ``dst``, the files as symlinks, kinds renamed by ``rename``."""
    man = json.loads(MANIFEST_PATH.read_text())
    models = {}
    for k in kinds:
        entry = dict(man["models"][k])
        entry["file"] = f"{rename(k)}_int8.onnx"
        entry["spec"] = {**entry["spec"], "kind": rename(k)}
        (dst / entry["file"]).symlink_to(MODELS_DIR / man["models"][k]["file"])
        models[rename(k)] = entry
    man["models"] = models
    man["error_model"]["models"] = {rename(k): v for k, v in man["error_model"]["models"].items()}
    (dst / "manifest.json").write_text(json.dumps(man))
    return man


def test_old_kind_manifest_is_mapped_and_its_error_model_still_fresh(tmp_path):
    """A manifest (and files) of the old kinds (``cden``, ``basenet``, ...) loads under today's
    names, with its error model recognised."""
    old = {v: k for k, v in LEGACY_KINDS.items()}
    man = _copy_models(tmp_path, rename=lambda k: old.get(k, k))
    assert "cden" in man["models"] and "basenet" in man["error_model"]["models"]
    nets = load_networks(tmp_path, threads=1)
    assert not nets.error_model_stale and nets.sigma == man["error_model"]["sigma"]
    assert nets.depth.path.name == "cden_int8.onnx" and nets.depth.spec["kind"] == "depth"
    assert nets.stem_base is not None and nets.rope_finder is not None


def test_optional_and_required_networks(tmp_path):
    _copy_models(tmp_path, kinds=("segmenter", "depth", "tree"))
    nets = load_networks(tmp_path, threads=1)
    assert nets.stem_base is None and nets.stem_edge is None and nets.rope_verifier is None and nets.rope_finder is None
    # the error model was measured with the stem-base network: without it, stale
    assert nets.error_model_stale
    man = json.loads((tmp_path / "manifest.json").read_text())
    man["models"]["stem_base"] = dict(load_manifest()["models"]["stem_base"])
    (tmp_path / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(MonodbhError, match=r"stem_base_int8.onnx: model file missing \(listed in"):
        load_networks(tmp_path, threads=1)   # listed but not copied: never measured without it
    (tmp_path / "manifest.json").write_text(json.dumps({**man, "models": {k: v for k, v in man["models"].items()
                                                                          if k != "stem_base"}}))
    (tmp_path / "tree_int8.onnx").unlink()
    with pytest.raises(MonodbhError, match="tree_int8.onnx: model file missing"):
        load_networks(tmp_path, threads=1)
    man = json.loads((tmp_path / "manifest.json").read_text())
    del man["models"]["tree"]
    (tmp_path / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(MonodbhError, match="no shipped 'tree' model"):
        load_networks(tmp_path, threads=1)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(MonodbhError, match="empty: no models here"):
        load_networks(empty)
    with pytest.raises(MonodbhError, match="nothing: no such folder"):
        load_networks(tmp_path / "nothing")
    with pytest.raises(MonodbhError, match="manifest.json: not a folder"):
        load_networks(tmp_path / "manifest.json")


def test_session_keeps_its_attributes(tmp_path):
    """``pipeline.Session`` takes its networks from :func:`load_networks` under its own names."""
    from monodbh.toolkit.pipeline import Session

    _copy_models(tmp_path)
    s = Session(tmp_path, threads=1)
    assert isinstance(s.segmenter, Segmenter) and isinstance(s.depth, DepthPredictor)
    assert isinstance(s.trees, TreePredictor) and isinstance(s.base, StemBaseFinder)
    assert isinstance(s.rope_verifier, RopeVerifier) and isinstance(s.rope_finder, RopeFinder)
    assert s.models_dir == tmp_path
    assert s.sigma_network == load_manifest()["error_model"]["sigma"] and not s.error_model_stale
    assert s.rank_network and s.distance_calibration and s.load_ms > 0
