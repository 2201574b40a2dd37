"""Stages of the measuring pipeline on small synthetic inputs (no networks needed)."""
import numpy as np
import pytest

from monodbh.calib import Camera
from monodbh.calib.errors import MonodbhError
from monodbh.toolkit.config import MeasureConfig
from monodbh.toolkit.frames import work_frame
from monodbh.toolkit.pipeline import _find_rope, _Request


class _Seg:
    def __init__(self, instance):
        self.instance = instance

    def result(self):
        return self


class _Sess:
    """What the rope stage needs of a Session: its config and the two rope networks (none here)."""
    config = MeasureConfig()
    rope_verifier = None
    rope_finder = None


def _roped_photo_near_corner(W=2000, H=1500):
    """A brown trunk near the top-left corner of a photo with a red rope across it (photo pixels)."""
    rng = np.random.default_rng(1)
    img = np.clip(np.full((H, W, 3), (70, 110, 60), np.float64) + rng.normal(0, 4, (H, W, 3)), 0, 255)
    img[:, 150:270] = (110, 90, 70)
    img[196:204, 150:270] = (190, 30, 30)
    return img.astype(np.uint8)


def test_a_tap_goes_through_the_lens_distortion():
    """``--pick`` is a photo pixel: near a corner of a distorted photo the working image's pixel is
    tens of pixels from the tap scaled alone; the rope tapped there must be found."""
    W, H = 2000, 1500
    cam = Camera([[1500.0, 0, 1000.0], [0, 1500.0, 750.0], [0, 0, 1]], [-0.25, 0.05, 0, 0, 0], (W, H))
    frame = work_frame(_roped_photo_near_corner(W, H), cam, 1600)
    tap = (210.0, 200.0)
    assert np.hypot(*(frame.to_work(tap) - np.asarray(tap) * frame.scale)) > 20
    instance = np.zeros(frame.shape, np.uint16)
    choice = _find_rope("p.jpg", frame, _Seg(instance), 8.0, _Request(pick_xy=tap), _Sess(), {})
    assert choice and np.hypot(*(frame.to_photo(choice.rope.center_xy) - tap)) < 25


def test_a_tap_far_from_any_rope_is_refused_with_the_photos_pixel():
    W, H = 2000, 1500
    cam = Camera([[1500.0, 0, 1000.0], [0, 1500.0, 750.0], [0, 0, 1]], [0, 0, 0, 0, 0], (W, H))
    frame = work_frame(_roped_photo_near_corner(W, H), cam, 1600)
    instance = np.zeros(frame.shape, np.uint16)
    with pytest.raises(MonodbhError, match=r"at the picked point \(1500,1000\)"):
        _find_rope("p.jpg", frame, _Seg(instance), 8.0, _Request(pick_xy=(1500.0, 1000.0)), _Sess(), {})
