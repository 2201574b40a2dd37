"""The measuring pipeline's own steps (toolkit.pipeline)."""
import numpy as np


def test_unproject_depth_matches_pinhole():
    from monodbh.toolkit.clouds import unproject_depth
    K = np.array([[500.0, 0, 160], [0, 480.0, 120], [0, 0, 1]])
    z = np.full((240, 320), 4.0, np.float32)
    z[100:, :] = 7.5
    for step in (1, 2):
        pts = unproject_depth(z, K, step)
        assert pts.shape == (240 // step, 320 // step, 3)
        v, u = 150 // step, 40 // step
        zz = z[v * step, u * step]
        np.testing.assert_allclose(pts[v, u], [(u * step - 160) / 500 * zz, (v * step - 120) / 480 * zz, zz],
                                   rtol=0, atol=0.02 * step)
