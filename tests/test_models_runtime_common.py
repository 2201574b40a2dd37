"""The runtime's shared part: no torch, the manifest (old kinds mapped at load), sessions, image and patch helpers."""
import json
import subprocess
import sys

import numpy as np
import pytest

from monodbh.calib.errors import MonodbhError
from monodbh.models.runtime.common import (LEGACY_KINDS, MEAN_RGB_U8, affine_inside, affine_region, canonical_kind,
                                           load_manifest, session_options, stack_feed, to_uint8)

MODULES = ("common", "segmenter", "depth", "tree", "stem_base", "rope_verifier", "rope_finder", "networks")


def test_runtime_does_not_import_torch():
    code = ("import sys, monodbh.models.runtime" + "".join(f", monodbh.models.runtime.{m}" for m in MODULES)
            + "; assert 'torch' not in sys.modules, 'torch imported'")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr


def test_manifest_missing_or_unreadable(tmp_path):
    assert load_manifest(tmp_path / "nope.json") == {"format": 1, "models": {}}
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(MonodbhError, match="bad.json: cannot read model manifest"):
        load_manifest(tmp_path / "bad.json")


def _old_manifest():
    return {"format": 1,
            "models": {"cden": {"file": "cden_int8.onnx", "sha256": "a", "spec": {"kind": "cden"}},
                       "segmenter": {"file": "segmenter_int8.onnx", "sha256": "s", "spec": {"kind": "segmenter"}},
                       "ropeseg": {"file": "ropeseg_int8.onnx", "sha256": "r"}},
            "error_model": {"sigma": {"network": 0.3}, "models": {"cden": "a", "segmenter": "s"}}}


def test_old_kind_manifest_is_read_under_todays_kinds(tmp_path):
    p = tmp_path / "manifest.json"
    p.write_text(json.dumps(_old_manifest()))
    man = load_manifest(p)
    assert set(man["models"]) == {"depth", "segmenter", "rope_finder"}
    assert man["models"]["depth"]["spec"]["kind"] == "depth"
    assert man["models"]["depth"]["file"] == "cden_int8.onnx"          # the file as it is on disk
    assert man["error_model"]["models"] == {"depth": "a", "segmenter": "s"}
    assert man["error_model"]["sigma"] == {"network": 0.3}


def test_manifest_naming_a_network_twice_is_refused(tmp_path):
    man = _old_manifest()
    man["models"]["depth"] = man["models"]["cden"]
    p = tmp_path / "manifest.json"
    p.write_text(json.dumps(man))
    with pytest.raises(MonodbhError, match=r"manifest.json: lists the 'depth' network twice .*'cden'"):
        load_manifest(p)


def test_canonical_kind():
    assert {canonical_kind(k) for k in LEGACY_KINDS} == {"depth", "tree", "stem_base", "rope_verifier",
                                                         "rope_finder"}
    assert canonical_kind("segmenter") == "segmenter" and canonical_kind(None) is None


def test_session_options_threads_and_spinning():
    so = session_options(3)
    assert so.intra_op_num_threads == 3 and so.inter_op_num_threads == 1
    assert so.get_session_config_entry("session.intra_op.allow_spinning") == "0"
    with pytest.raises(Exception):          # spinning: onnxruntime's own default, no entry
        session_options(spin=True).get_session_config_entry("session.intra_op.allow_spinning")


def test_stack_feed_and_to_uint8():
    rgb = np.full((4, 6, 3), 128, np.uint8)
    flag = np.zeros((4, 6), bool)
    flag[1] = True
    x = stack_feed(rgb, flag, ~flag)
    assert x.shape == (5, 4, 6) and x.dtype == np.float32 and x.flags.c_contiguous
    assert x[3, 1].all() and not x[3, 0].any() and (x[4] == 1 - x[3]).all()
    assert to_uint8(np.array([-3.0, 0.49, 0.5, 254.6, 300.0])).tolist() == [0, 0, 1, 255, 255]
    assert MEAN_RGB_U8.tolist() == [124, 116, 104]


def test_affine_region_and_inside():
    A = np.array([[1.0, 0.0, 10.0], [0.0, 1.0, -3.0]])        # patch (col, row) -> photo (col + 10, row - 3)
    x0, y0, x1, y1 = affine_region(A, 8, 6, 1.0, 100, 50)
    assert (x0, y0) == (6, 0) and (x1, y1) == (22, 7)           # 4 px of padding, clipped at the top
    inside = affine_inside(A, 8, 6, 100, 50)
    assert inside.shape == (6, 8) and not inside[:3].any() and inside[3:].all()
    assert affine_region(A, 8, 6, 1.0, 5, 50)[2] <= affine_region(A, 8, 6, 1.0, 5, 50)[0]   # off the photo: empty
