"""Photo <-> working-image pixels (toolkit/frames.py) and taps mapped through them."""
import numpy as np
import pytest

from monodbh.calib import Camera
from monodbh.toolkit.frames import rescale_intrinsics, work_frame

DIST = [-0.06, 0.03, 1e-4, -2e-4, 0.0]


def _camera(W=4000, H=3000, dist=DIST):
    return Camera([[3000.0 * W / 4000, 0, 0.4975 * W], [0, 3000.0 * W / 4000, 0.504 * H], [0, 0, 1]], dist, (W, H))


def test_reported_pixels_are_the_photos_own_and_round_trip_a_tap():
    """A 12 MP photo is measured at 1600 px and undistorted: a point the pipeline reports (the
    rope, a refused band) must come back in the photo's pixels, where ``--pick`` reaches it."""
    W, H = 4000, 3000
    frame = work_frame(np.zeros((H, W, 3), np.uint8), _camera(), 1600)
    assert max(frame.scale) < 0.5 and frame.shape == (1200, 1600)
    for xy in [(12.0, 20.0), (2000.0, 1500.0), (3985.0, 2990.0), (300.0, 2700.0)]:
        assert np.allclose(frame.to_photo(frame.to_work(xy)), xy, atol=0.05)
    # near a corner, dividing by the scale alone is tens of pixels off
    w = frame.to_work((12.0, 20.0))
    assert np.hypot(*(w / np.asarray(frame.scale) - (12.0, 20.0))) > 10


def test_no_distortion_is_a_pure_rescale():
    frame = work_frame(np.zeros((300, 400, 3), np.uint8), _camera(400, 300, dist=[0, 0, 0, 0, 0]), 200)
    assert frame.scale == (0.5, 0.5)
    assert np.allclose(frame.to_work((10.0, 20.0)), (4.75, 9.75))
    assert np.allclose(frame.to_photo((4.75, 9.75)), (10.0, 20.0))


def test_rescale_intrinsics_round_trip():
    K = np.array([[1234.5, 0, 1999.5], [0, 1230.0, 1499.5], [0, 0, 1]])
    K2 = rescale_intrinsics(K, 0.4, 0.4)
    assert K2[0, 0] == pytest.approx(493.8) and K2[0, 2] == pytest.approx(799.5)
    assert np.allclose(rescale_intrinsics(K2, 0.4, 0.4, inverse=True), K)


def test_full_res_crop_without_distortion_is_the_photo():
    rgb = np.random.default_rng(0).integers(0, 255, (300, 400, 3), np.uint8)
    frame = work_frame(rgb, _camera(400, 300, dist=[0, 0, 0, 0, 0]), 200)
    crop = frame.full_res_crop(rgb, _camera(400, 300, dist=[0, 0, 0, 0, 0]), (-5, 10, 50, 40))
    assert crop.shape == (30, 55, 3)
    assert (crop[:, :5] == 0).all() and (crop[:, 5:] == rgb[10:40, 0:50]).all()
