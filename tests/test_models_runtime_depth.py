"""The depth network's runtime: letterbox geometry, the depth code, the predictor on a tiny exported model."""
import numpy as np
import pytest

from monodbh.models.runtime.depth import DepthPredictor, letterbox, letterbox_geometry, unletterbox


def test_letterbox_roundtrip():
    assert letterbox_geometry(4000, 3000, 256) == (0.064, 0, 32, 256, 192)
    a = np.random.default_rng(0).random((48, 64)).astype(np.float32)
    lb = letterbox(a, 64, "nearest")
    assert lb.shape == (64, 64) and np.all(lb[:8] == 0)
    np.testing.assert_allclose(unletterbox(lb, 64, 48), a)
    m = letterbox(np.ones((30, 20), bool), 16, "mask")
    assert m.dtype == bool and m[:, :2].sum() == 0 and m[:, 4:12].all()


@pytest.fixture(scope="module")
def tiny_depth(tmp_path_factory):
    torch = pytest.importorskip("torch")
    from monodbh.models.export.onnx_io import export_onnx
    from monodbh.models.modeling import build

    torch.manual_seed(0)
    m = build("depth", "tiny").eval()
    path = tmp_path_factory.mktemp("depth") / "depth.onnx"
    export_onnx(m, m.spec, path, check=False)
    return path


def test_depth_predictor_tiny(tiny_depth):
    p = DepthPredictor(tiny_depth, threads=1)
    assert p.size == 64 and p.extra["depth_code"]["d_max_m"] == 100.0
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (75, 100, 3), dtype=np.uint8)
    mask = np.zeros((75, 100), bool)
    mask[:, 40:50] = True
    fx = 80.0
    d = p.predict(rgb, mask, fx)
    assert d.shape == (75, 100) and d.dtype == np.float32
    fx_net = fx * 64 / 100
    lo, hi = 0.5 * fx_net / (0.8 * 64), 100.0 * fx_net / (0.8 * 64)
    assert np.all(d >= lo * 0.999) and np.all(d <= hi * 1.001)
    # portrait photo works too
    assert p.predict(rgb.transpose(1, 0, 2).copy(), mask.T.copy(), fx).shape == (100, 75)
    # mirror-image averaging: the depth of a mirrored photo is the mirrored depth, and it is
    # the mean log-depth code of the two single passes
    assert np.allclose(p.predict(rgb[:, ::-1].copy(), mask[:, ::-1].copy(), fx), d[:, ::-1], rtol=1e-4)
    one = DepthPredictor(tiny_depth, threads=1, flip_tta=False)
    a, b = one.predict(rgb, mask, fx), one.predict(rgb[:, ::-1].copy(), mask[:, ::-1].copy(), fx)[:, ::-1]
    assert not np.allclose(a, b, rtol=1e-3)
    assert np.allclose(d, np.sqrt(a * b), rtol=1e-3)         # the code is linear in log depth


def test_predictor_missing_file_is_user_error(tmp_path):
    from monodbh.calib.errors import MonodbhError

    with pytest.raises(MonodbhError, match="not found"):
        DepthPredictor(tmp_path / "nope.onnx")
    with pytest.raises(MonodbhError, match="no shipped 'depth'"):
        DepthPredictor(manifest={"format": 1, "models": {}})


def test_depth_predictor_reads_a_legacy_kind_file(tiny_depth, tmp_path):
    """A file exported before the rename says ``cden`` in its metadata: it is the depth network."""
    import json

    onnx = pytest.importorskip("onnx")
    from monodbh.models.export.onnx_io import SPEC_METADATA_KEY

    m = onnx.load(str(tiny_depth))
    for p in m.metadata_props:
        if p.key == SPEC_METADATA_KEY:
            spec = json.loads(p.value)
            assert spec["kind"] == "depth"
            p.value = json.dumps({**spec, "kind": "cden"})
    onnx.save(m, str(tmp_path / "cden.onnx"))
    assert DepthPredictor(tmp_path / "cden.onnx", threads=1).spec["kind"] == "depth"


def test_depth_code_to_metric_in_place_equals_the_expression():
    """Computed step by step in one buffer: bit for bit the plain float32 expression."""
    import math

    from monodbh.models.runtime.depth import D_MAX, D_MIN, F_CANON_FRAC, depth_code_to_metric

    t = np.random.default_rng(2).uniform(-1, 1, (47, 61)).astype(np.float32)
    lo = math.log(D_MIN)
    want = (np.exp(lo + (t + 1.0) * 0.5 * (math.log(D_MAX) - lo)) * (123.4 / (F_CANON_FRAC * 256))).astype(np.float32)
    got = depth_code_to_metric(t, 123.4, 256)
    assert got.dtype == np.float32 and np.array_equal(got, want)
    assert np.array_equal(t, np.random.default_rng(2).uniform(-1, 1, (47, 61)).astype(np.float32))   # input kept
