"""The tree network's runtime: crop geometry, silhouette units, the predictor on a tiny exported model."""
import numpy as np
import pytest

from monodbh.models.runtime.tree import (TreePredictor, crop_square, ray_cos_map, silhouette_targets,
                                         silhouette_to_metric)


@pytest.fixture(scope="module")
def tiny_tree(tmp_path_factory):
    torch = pytest.importorskip("torch")
    from monodbh.models.export.onnx_io import export_onnx
    from monodbh.models.modeling import build

    torch.manual_seed(0)
    m = build("tree", "tiny").eval()
    path = tmp_path_factory.mktemp("tree") / "tree.onnx"
    export_onnx(m, m.spec, path, check=False)
    return path


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


def test_tree_predictor_tiny(tiny_tree):
    p = TreePredictor(tiny_tree, threads=1)
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


def test_no_shipped_tree_network_is_user_error():
    from monodbh.calib.errors import MonodbhError

    with pytest.raises(MonodbhError, match="no shipped 'tree'"):
        TreePredictor(manifest={"format": 1, "models": {}})
