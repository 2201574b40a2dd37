"""runtime_gan: crop/letterbox geometry and the two predictors on tiny exported models."""
import subprocess
import sys

import numpy as np
import pytest

from monodbh.models.runtime_gan import (DepthPredictor, TreePredictor, crop_square, letterbox,
                                        letterbox_geometry, ray_cos_map, silhouette_targets,
                                        silhouette_to_metric, unletterbox)


def test_runtime_gan_does_not_import_torch():
    code = ("import sys, monodbh.models.runtime_gan as r; "
            "assert 'torch' not in sys.modules, 'torch imported'; print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr


def test_crop_square_pixel_alignment():
    img = np.zeros((100, 120, 3), np.uint8)
    img[..., 0] = np.arange(120)[None]
    img[..., 1] = np.arange(100)[:, None]
    c = crop_square(img, (50.5, 40.5), 16, 16)          # unit scale: integer shift
    assert tuple(c[0, 0, :2]) == (43, 33) and tuple(c[15, 15, :2]) == (58, 48)
    far = crop_square(img, (-100, -100), 30, 8)          # fully outside: mean colour
    assert np.all(far == far[0, 0]) and far[0, 0, 0] == 124
    m = np.zeros((100, 120), bool)
    m[30:50, 40:60] = True
    assert crop_square(m, (50, 40), 40, 20, "mask").sum() == 100


def test_letterbox_roundtrip():
    assert letterbox_geometry(4000, 3000, 256) == (0.064, 0, 32, 256, 192)
    a = np.random.default_rng(0).random((48, 64)).astype(np.float32)
    lb = letterbox(a, 64, "nearest")
    assert lb.shape == (64, 64) and np.all(lb[:8] == 0)
    np.testing.assert_allclose(unletterbox(lb, 64, 48), a)
    m = letterbox(np.ones((30, 20), bool), 16, "mask")
    assert m.dtype == bool and m[:, :2].sum() == 0 and m[:, 4:12].all()


def test_silhouette_metric_roundtrip():
    z1 = np.array([2.9, 3.0]); z2 = np.array([3.1, 3.3])
    R, G = silhouette_targets(z1, z2, 3.0, 40.0, 500.0)
    f, b = silhouette_to_metric(R, G, 3.0, 40.0, 500.0)
    np.testing.assert_allclose(f, z1, rtol=1e-6)
    np.testing.assert_allclose(b, z2, rtol=1e-6)


def test_ray_thickness_roundtrip_and_geometry():
    """Along-ray thickness: a round stem seen off-axis is thinner in z than along its ray."""
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    cos = ray_cos_map((320 - 20.0, 240 - 20.0, 40.0), 4, K)
    assert cos.shape == (4, 4) and cos.max() <= 1.0 and cos.min() > 0.99
    far = ray_cos_map((820.0, 240 - 20.0, 40.0), 4, K)        # 520-560 px right: ~47 deg off
    assert np.all(np.diff(far, axis=1) < 0)                    # cos falls away from the centre
    np.testing.assert_allclose(far[1, 0], 1 / np.hypot(1, (820 + 5 - 320) / 500), rtol=1e-3, atol=2e-3)
    z1 = np.full((4, 4), 3.0); z2 = z1 + 0.3 * far               # 0.3 m along every ray
    R, G = silhouette_targets(z1, z2, 3.0, 40.0, 500.0, far)
    np.testing.assert_allclose(G, 0.3 * 500 / (3.0 * 40.0), rtol=1e-5)
    f, b = silhouette_to_metric(R, G, 3.0, 40.0, 500.0, far)
    np.testing.assert_allclose(b, z2, rtol=1e-6)


@pytest.fixture(scope="module")
def tiny_models(tmp_path_factory):
    torch = pytest.importorskip("torch")
    from monodbh.models.export.onnx_io import export_onnx
    from monodbh.models.modeling import build

    d = tmp_path_factory.mktemp("gan")
    torch.manual_seed(0)
    paths = {}
    for kind in ("cden", "treenet"):
        m = build(kind, "tiny").eval()
        paths[kind] = d / f"{kind}.onnx"
        export_onnx(m, m.spec, paths[kind], check=False)
    return paths


def test_depth_predictor_tiny(tiny_models):
    p = DepthPredictor(tiny_models["cden"], threads=1)
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
    one = DepthPredictor(tiny_models["cden"], threads=1, flip_tta=False)
    a, b = one.predict(rgb, mask, fx), one.predict(rgb[:, ::-1].copy(), mask[:, ::-1].copy(), fx)[:, ::-1]
    assert not np.allclose(a, b, rtol=1e-3)
    assert np.allclose(d, np.sqrt(a * b), rtol=1e-3)         # the code is linear in log depth


def test_tree_predictor_tiny(tiny_models):
    p = TreePredictor(tiny_models["treenet"], threads=1)
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 255, (120, 160, 3), dtype=np.uint8)
    m = np.zeros((120, 160), bool)
    m[:, 70:90] = True
    R, G, box = p.predict(rgb, m, (80.0, 60.0), 20.0, 300.0)
    assert R.shape == G.shape == (64, 64) and R.dtype == np.float32
    assert np.abs(R).max() <= 1 and np.abs(G).max() <= 1
    assert box == (40.0, 20.0, 80.0)                      # k = 4: side 4 x 20 px
    _, _, box = p.predict(rgb, m, (80.0, 60.0), 2.0, 300.0)
    assert box[2] == 24.0                                  # minimum crop side
    assert p.thickness == "ray"                            # the spec of the current models
    with pytest.raises(ValueError, match="needs K"):
        p.to_metric(R, G, 5.0, (40.0, 20.0, 80.0), 300.0)
    K = np.array([[300.0, 0, 80], [0, 300.0, 60], [0, 0, 1]])
    zf, zb = p.to_metric(R, G, 5.0, (40.0, 20.0, 80.0), 300.0, K)
    np.testing.assert_allclose(zf, 5.0 * (1 + R * 80 / 300), rtol=1e-5)
    cos = ray_cos_map((40.0, 20.0, 80.0), 64, K)
    np.testing.assert_allclose(zb - zf, 5.0 * G * 80 / 300 * cos, rtol=1e-4, atol=1e-6)
    assert zf.shape == (64, 64) and zb.shape == (64, 64)


def test_predictor_missing_file_is_user_error(tmp_path):
    from monodbh.calib.errors import MonodbhError

    with pytest.raises(MonodbhError, match="not found"):
        DepthPredictor(tmp_path / "nope.onnx")
    with pytest.raises(MonodbhError, match="no shipped 'treenet'"):
        TreePredictor(manifest={"format": 1, "models": {}})


def test_depth_code_to_metric_in_place_equals_the_expression():
    """Computed step by step in one buffer: bit for bit the plain float32 expression."""
    import math

    from monodbh.models.runtime_gan import D_MAX, D_MIN, F_CANON_FRAC, depth_code_to_metric

    t = np.random.default_rng(2).uniform(-1, 1, (47, 61)).astype(np.float32)
    lo = math.log(D_MIN)
    want = (np.exp(lo + (t + 1.0) * 0.5 * (math.log(D_MAX) - lo)) * (123.4 / (F_CANON_FRAC * 256))).astype(np.float32)
    got = depth_code_to_metric(t, 123.4, 256)
    assert got.dtype == np.float32 and np.array_equal(got, want)
    assert np.array_equal(t, np.random.default_rng(2).uniform(-1, 1, (47, 61)).astype(np.float32))   # input kept
