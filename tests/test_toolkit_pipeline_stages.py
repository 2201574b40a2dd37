"""Stages of the measuring pipeline on small synthetic inputs (no networks needed)."""
import numpy as np
import pytest

from monodbh.calib import Camera
from monodbh.calib.errors import MonodbhError
from monodbh.toolkit.config import MeasureConfig
from monodbh.toolkit.frames import work_frame
from monodbh.toolkit.pipeline import _find_rope, _Request, _TapInstances


class _Seg:
    def __init__(self, instance):
        self.instance = instance

    def result(self):
        return self


class _NoTreeSeg:
    """A segmenter stub that finds no tree (the second pass at a tap)."""

    def predict(self, rgb, size):
        from types import SimpleNamespace
        return SimpleNamespace(instance=np.zeros(rgb.shape[:2], np.int32))


class _Sess:
    """What the rope stage needs of a Session: its config, the segmenter (for a second pass at a
    tap) and the two rope networks (none here)."""
    config = MeasureConfig()
    segmenter = _NoTreeSeg()
    rope_verifier = None
    rope_finder = None


def _find(frame, instance, req, cell=8.0):
    return _find_rope("p.jpg", frame, _TapInstances(_Sess(), frame, _Seg(instance), req, cell), cell, req, _Sess(), {})


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
    choice = _find(frame, instance, _Request(pick_xy=tap))
    assert choice and np.hypot(*(frame.to_photo(choice.rope.center_xy) - tap)) < 25


def test_a_tap_far_from_any_rope_is_refused_with_the_photos_pixel():
    W, H = 2000, 1500
    cam = Camera([[1500.0, 0, 1000.0], [0, 1500.0, 750.0], [0, 0, 1]], [0, 0, 0, 0, 0], (W, H))
    frame = work_frame(_roped_photo_near_corner(W, H), cam, 1600)
    instance = np.zeros(frame.shape, np.uint16)
    with pytest.raises(MonodbhError, match=r"at the picked point \(1500,1000\)"):
        _find(frame, instance, _Request(pick_xy=(1500.0, 1000.0)))


class _CropSeg:
    """A segmenter stub: instance 7 on the columns 40-59 of the full image, seen through any crop."""

    def __init__(self, x_offset_of):
        self.x_offset_of, self.calls = x_offset_of, []

    def predict(self, rgb, size):
        from types import SimpleNamespace
        self.calls.append((rgb.shape, size))
        x0 = self.x_offset_of(rgb)
        inst = np.zeros(rgb.shape[:2], np.int32)
        cols = np.arange(rgb.shape[1]) + x0
        inst[:, (cols >= 40) & (cols < 60)] = 7
        return SimpleNamespace(instance=inst)


def test_the_zoomed_edge_mask_is_the_stem_under_the_rope_in_a_crop_around_it():
    from types import SimpleNamespace

    from monodbh.toolkit.pipeline import _zoomed_stem_mask
    H, W = 200, 300
    img = np.tile(np.arange(W, dtype=np.uint8)[None, :, None], (H, 1, 3))   # column index as colour
    frame = SimpleNamespace(shape=(H, W), image=img)
    seg = _CropSeg(lambda rgb: int(rgb[0, 0, 0]))
    sess = SimpleNamespace(segmenter=seg)
    m = _zoomed_stem_mask(sess, frame, (50.0, 100.0), 0.3)
    (shape, size), = seg.calls
    assert shape[:2] == (90, 90) and size == (90, 90)          # 0.3 x 300 px, square
    ys, xs = np.nonzero(m)
    assert xs.min() == 40 and xs.max() == 59                    # mapped back to the photo's columns
    assert ys.min() == 55 and ys.max() == 144                   # the crop's rows only
    assert _zoomed_stem_mask(sess, frame, (150.0, 100.0), 0.3) is None    # no stem under the rope


def test_a_tap_where_the_photo_has_no_tree_adds_the_tree_a_close_up_finds_there():
    from types import SimpleNamespace
    H, W = 200, 300
    img = np.tile(np.arange(W, dtype=np.uint8)[None, :, None], (H, 1, 3))   # column index as colour
    frame = SimpleNamespace(shape=(H, W), image=img, to_work=lambda xy: np.asarray(xy, float))
    whole = np.zeros((H, W), np.int32)
    whole[:, 200:220] = 3                                       # another tree, far from the tap
    seg = _CropSeg(lambda rgb: int(rgb[0, 0, 0]))
    sess = SimpleNamespace(segmenter=seg, config=MeasureConfig())
    at_tap = _TapInstances(sess, frame, _Seg(whole), _Request(pick_xy=(50.0, 100.0)), 4.0)
    assert at_tap() is whole and not seg.calls                 # the photo's own until asked
    assert at_tap.add_tree_at_tap() and at_tap.added and len(seg.calls) == 1
    inst = at_tap()
    ys, xs = np.nonzero(inst == 4)                              # a new id, after the photo's own
    assert xs.min() == 40 and xs.max() == 59 and ys.min() == 55 and ys.max() == 144
    assert (inst == 3).sum() == (whole == 3).sum()
    assert not at_tap.add_tree_at_tap() and len(seg.calls) == 1              # once
    on_tree = _TapInstances(sess, frame, _Seg(whole), _Request(pick_xy=(210.0, 100.0)), 4.0)
    assert not on_tree.add_tree_at_tap() and on_tree() is whole and len(seg.calls) == 1
    no_tap = _TapInstances(sess, frame, _Seg(whole), _Request(), 4.0)
    assert not no_tap.add_tree_at_tap() and len(seg.calls) == 1
    nothing_there = _TapInstances(sess, frame, _Seg(whole), _Request(pick_xy=(150.0, 100.0)), 4.0)
    assert not nothing_there.add_tree_at_tap() and nothing_there() is whole   # the close-up finds none


def test_edge_mask_zoom_is_checked():
    assert MeasureConfig(edge_mask_zoom=None).edge_mask_zoom is None
    with pytest.raises(ValueError, match="edge_mask_zoom"):
        MeasureConfig(edge_mask_zoom=0.0)


def test_a_faint_row_much_thinner_than_the_known_marker_is_refused_or_flagged_at_a_tap():
    from types import SimpleNamespace

    from monodbh.toolkit.pipeline import _check_row_against_marker
    from monodbh.toolkit.result import MeasureResult
    from monodbh.toolkit.rope.select import RopeChoice, RopeSource
    frame = SimpleNamespace(camera=SimpleNamespace(K=np.array([[1300.0, 0, 800], [0, 1300.0, 600], [0, 0, 1]])),
                            to_photo=lambda xy: np.asarray(xy, float) / 0.4)
    row = RopeChoice(SimpleNamespace(center_xy=(100.0, 50.0)), source=RopeSource.STEM_VERIFIED)
    measured = lambda: MeasureResult(photo="p.jpg", dbh_cm=13.3, distance_m=2.0)
    # an 8 mm marker at 2 m is 5.2 px thick: not a sub-pixel row
    with pytest.raises(MonodbhError, match=r"p.jpg: no red rope found \(the faint red row at \(250,125\).*8 mm.*5 px"):
        _check_row_against_marker(measured(), "p.jpg", frame, row, _Request(rope_diameter_m=0.008), 4.0)
    res = measured()
    _check_row_against_marker(res, "p.jpg", frame, row, _Request(pick_xy=(250.0, 125.0), rope_diameter_m=0.008), 4.0)
    assert res.dbh_cm == 13.3 and res.flags == ["row_thinner_than_marker"]
    for req, choice in ((_Request(rope_diameter_m=0.005), row),                   # 3.2 px: could be it
                        (_Request(), row),                                         # width not known
                        (_Request(rope_diameter_m=0.008), RopeChoice(row.rope, source=RopeSource.BAND))):
        res = measured()
        _check_row_against_marker(res, "p.jpg", frame, choice, req, 4.0)
        assert res.dbh_cm == 13.3 and not res.flags


def test_a_distance_where_no_marker_is_seen_or_a_giant_dbh_is_refused_as_implausible():
    from types import SimpleNamespace

    from monodbh.toolkit.pipeline import _check_plausible
    from monodbh.toolkit.result import MeasureResult
    # a 1280 px working image of a 3200 px photo: fx 1000 there, 2500 in the photo's pixels
    frame = SimpleNamespace(camera=SimpleNamespace(K=np.array([[1000.0, 0, 640], [0, 1000.0, 480], [0, 0, 1]])),
                            scale=(0.4, 0.4))
    cfg = MeasureConfig()
    _check_plausible(MeasureResult(photo="p.jpg", dbh_cm=40.0, distance_m=120.0), "p.jpg", frame, cfg)
    with pytest.raises(MonodbhError, match=r"p.jpg: implausible result \(DBH 900 cm at 130 m.*beyond 125 m"):
        _check_plausible(MeasureResult(photo="p.jpg", dbh_cm=900.0, distance_m=130.0), "p.jpg", frame, cfg)
    with pytest.raises(MonodbhError, match=r"implausible result \(DBH 600 cm at 10 m: over 500 cm\)"):
        _check_plausible(MeasureResult(photo="p.jpg", dbh_cm=600.0, distance_m=10.0), "p.jpg", frame, cfg)
