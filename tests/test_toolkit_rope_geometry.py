"""Distances to a rope band, red running on into it and the tree instance at a point (monodbh.toolkit.rope.geometry)."""
from types import SimpleNamespace

import numpy as np

from monodbh.toolkit.rope.geometry import (distance_to_band, distance_to_chord, distance_to_vertices,
                                           instance_at_or_near, instance_in_window, red_path_to_band,
                                           trunk_run)


def test_vertex_distance_keeps_the_polyline_dtype_and_the_chord_is_a_segment():
    line = np.array([[0.0, 0.0], [10.0, 0.0]], np.float32)
    xy = (5.0, 3.0)
    d32 = distance_to_vertices(line, xy)
    assert d32 == float(np.float32(np.hypot(np.float32(5.0), np.float32(3.0))))
    assert distance_to_vertices(line.astype(np.float64), xy) == float(np.hypot(5.0, 3.0))
    assert distance_to_chord(line, xy) == 3.0
    assert distance_to_chord(line, (-4.0, 3.0)) == 5.0                 # beyond an end: to the end


def test_distance_to_band_without_a_centre_line_is_to_the_middle():
    rope = SimpleNamespace(polyline=None, center_xy=(3.0, 4.0))
    assert distance_to_band(rope, (0.0, 0.0)) == 5.0
    rope = SimpleNamespace(polyline=np.array([[0.0, 0.0], [10.0, 0.0]], np.float32), center_xy=(5.0, 0.0))
    assert distance_to_band(rope, (10.0, 2.0)) == 2.0


def test_instance_near_a_point():
    inst = np.zeros((50, 60), np.int32)
    inst[:, 20:30] = 2
    inst[:, 40:42] = 5
    assert instance_at_or_near(inst, (25.0, 10.0), 3) == 2             # under the point
    assert instance_at_or_near(inst, (33.0, 10.0), 6) == 2             # nearest, most frequent
    assert instance_at_or_near(inst, (10.0, 10.0), 3) == 0             # none within the radius
    assert instance_at_or_near(inst, (-40.0, 10.0), 3) == 0            # clipped into the image
    assert instance_in_window(inst, (38.0, 10.0), 3) == 5              # no preference for the point
    assert instance_in_window(inst, (33.0, 10.0), 10) == 2


def test_trunk_run_along_the_rope():
    mask = np.zeros((40, 100), bool)
    mask[:, 30:61] = True
    poly = np.array([[35.0, 20.0], [55.0, 20.0]])
    assert trunk_run(mask, poly, 45.0) == (30, 60)
    assert trunk_run(mask, poly, 62.0) == (30, 60)                      # a mask pixel within 3 columns
    assert trunk_run(mask, poly, 80.0) == (0, -1)


def _ring_and_loose_end():
    """A red ring 3 px thick across a grey trunk, a loose end hanging from its right end, a red
    blob elsewhere on the trunk."""
    img = np.full((120, 120, 3), (110, 105, 100), np.uint8)
    img[:, 30:90] = (90, 80, 70)                        # the trunk
    img[40:43, 30:90] = (190, 40, 30)                   # the ring
    img[40:100, 88:91] = (180, 40, 30)                  # its loose end
    img[70:76, 40:46] = (190, 40, 30)                   # red paint, not connected
    band = SimpleNamespace(polyline=np.array([[30.0, 41.0], [89.0, 41.0]]), center_xy=(59.5, 41.0), thickness_px=3.0)
    return img, band


def test_a_point_on_the_loose_end_runs_on_in_red_to_the_band():
    img, band = _ring_and_loose_end()
    assert red_path_to_band(img, band, (89.0, 90.0), reach_px=100)
    assert red_path_to_band(img, band, (92.5, 90.0), reach_px=100)        # a tap beside it
    assert not red_path_to_band(img, band, (60.0, 90.0), reach_px=100)    # bark
    assert not red_path_to_band(img, band, (43.0, 73.0), reach_px=100)    # red, but apart
    assert not red_path_to_band(img, band, (89.0, 90.0), reach_px=30)     # beyond the reach
