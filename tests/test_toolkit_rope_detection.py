"""What the rope detectors return (monodbh.toolkit.rope.detection)."""
import dataclasses

import numpy as np
import pytest

from monodbh.toolkit.rope.detection import RopeCandidate, RopeDetection


def test_a_detection_is_falsy_without_a_rope_and_both_are_frozen():
    assert not RopeDetection(False, "nothing") and RopeDetection(True)
    c = RopeCandidate(center_xy=(1.0, 2.0), direction=(1.0, 0.0), length_px=30.0, thickness_px=2.0,
                      polyline=np.zeros((2, 2), np.float32))
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.score = 1.0
    assert np.isnan(c.span) and c.as_dict() == dict(center_xy=[1.0, 2.0], direction=[1.0, 0.0], length_px=30.0,
                                                     thickness_px=2.0, score=0.0)
