"""The rope cascade (toolkit/rope/select.py): its checks and the choice it returns."""
from types import SimpleNamespace

import numpy as np

from monodbh.toolkit.rope.select import Refusal, RopeChoice, RopeSource, rope_across_trunk


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
