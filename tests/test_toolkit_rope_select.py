"""The rope cascade (toolkit/rope/select.py): its checks and the choice it returns."""
from types import SimpleNamespace

import numpy as np

from monodbh.toolkit.rope.select import Refusal, RopeChoice, RopeSource, rope_across_trunk, select_rope


def test_rope_across_trunk_check():
    inst = np.zeros((200, 300), np.int32)
    inst[:, 100:160] = 3                                       # a 60 px wide trunk
    band = lambda x0, x1, y=100: SimpleNamespace(center_xy=((x0 + x1) / 2, y), direction=(1.0, 0.0),
                                                 polyline=np.array([[x0, y], [x1, y]], np.float32))
    assert rope_across_trunk(band(100, 160), inst, cell=4)     # spans the trunk
    assert not rope_across_trunk(band(120, 130), inst, cell=4)  # a short dash on bark
    assert not rope_across_trunk(band(10, 60), inst, cell=4)    # off the trunk
    assert not rope_across_trunk(band(20, 290), inst, cell=4)   # far wider than the trunk


def test_choice_says_which_detector_and_its_flags():
    ok = RopeChoice(SimpleNamespace(found=True), source=RopeSource.STEM_VERIFIED)
    assert ok and ok.flags == ["rope_from_stem_profile", "rope_verified_by_network"]
    assert not RopeSource.STEM_PROFILE.spans_stem and RopeSource.FINDER.spans_stem
    assert RopeSource.BAND.is_line and not RopeSource.FINDER.is_line
    assert RopeChoice(None, source=RopeSource.FINDER_OVER_CLASSICAL).flags == [
        "rope_found_by_network", "rope_chosen_by_network"]
    refused = RopeChoice(SimpleNamespace(found=False), refusal=Refusal.WEAK_OFF_TRUNK)
    assert not refused and refused.flags == []


class _RefusingView:
    """A rope finder view that sees no rope anywhere (as the finder sees a wide strap)."""

    def __init__(self):
        self.looked = 0

    def near(self, xy):
        self.looked += 1
        return []

    def whole(self):
        self.looked += 1
        return []


def test_the_finder_check_refuses_a_band_it_cannot_see_unless_the_marker_is_wide():
    from monodbh.toolkit.rope.config import RopeConfig
    from monodbh.toolkit.rope.select import _finder_stage, _State

    class Band(SimpleNamespace):
        def __bool__(self):
            return True
    band = Band(found=True, ambiguous=False, weak=False, center_xy=(100.0, 50.0), thickness_px=12.0,
                polyline=np.array([[60.0, 50.0], [140.0, 50.0]], np.float32), direction=(1.0, 0.0))
    cfg = RopeConfig()
    st, view = _State(band, RopeSource.BAND), _RefusingView()
    _finder_stage(view, (200, 300), st, None, cfg)                  # a rope-width marker: checked
    assert view.looked and st.source is None                         # ... and refused
    st, view = _State(band, RopeSource.BAND), _RefusingView()
    _finder_stage(view, (200, 300), st, None, cfg, check=False)      # a strap wider than the finder knows
    assert view.looked == 0 and st.source is RopeSource.BAND and st.rope is band
    assert cfg.finder_check_max_marker_mm == 15.0


def test_a_tap_on_the_ropes_loose_end_measures_the_ring_and_says_so():
    img = np.full((240, 320, 3), (120, 125, 115), np.uint8)
    img[:, 130:190] = (95, 85, 72)                             # a trunk
    img[100:103, 130:190] = (185, 45, 35)                      # the rope round it
    img[100:170, 187:190] = (180, 42, 32)                      # a loose end hanging from the knot
    inst = np.zeros((240, 320), np.int32)
    inst[:, 130:190] = 1
    on_end = select_rope(img, lambda: inst, 4.0, pick_xy=(188, 150))
    assert on_end and on_end.source is RopeSource.BAND and on_end.flags == ["pick_on_rope_end"]
    assert abs(on_end.rope.center_xy[1] - 101) < 1.5
    on_ring = select_rope(img, lambda: inst, 4.0, pick_xy=(160, 101))
    assert on_ring and on_ring.flags == []
    on_bark = select_rope(img, lambda: inst, 4.0, pick_xy=(150, 200))
    assert on_bark.refusal is Refusal.PICK_MISSED


class _OneBandView:
    """A rope finder view that marks one band, 60 px long, through (160, 101)."""

    def near(self, xy):
        from monodbh.models.runtime.rope_finder import RopeComponent
        return [RopeComponent(center_xy=(160.0, 101.0), direction=(1.0, 0.0), length_px=60.0, thickness_px=3.0,
                              peak=6.0, mass=40.0, n=60, polyline=np.array([[130.0, 101.0], [190.0, 101.0]],
                                                                           np.float32))]

    def whole(self):
        return self.near(None)


def test_at_a_tap_the_finders_band_replaces_a_stem_search_row():
    from monodbh.toolkit.rope.config import RopeConfig
    from monodbh.toolkit.rope.select import _finder_stage, _State

    row = SimpleNamespace(found=True, ambiguous=False, weak=False, center_xy=(240.0, 101.0),
                          polyline=np.array([[100.0, 101.0], [380.0, 101.0]], np.float32))
    st = _State(row, RopeSource.STEM_PROFILE)
    _finder_stage(_OneBandView(), (240, 400), st, (160.0, 101.0), RopeConfig())
    assert st.source is RopeSource.FINDER and abs(st.rope.center_xy[0] - 160.0) < 1.0
    st = _State(row, RopeSource.STEM_PROFILE)
    _finder_stage(_RefusingView(), (240, 400), st, (160.0, 101.0), RopeConfig())      # no band there
    assert st.source is RopeSource.STEM_PROFILE and st.rope is row
