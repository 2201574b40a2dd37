"""evaluation.position_bench: the true tree position from a record's pose, and the EXIF it writes."""
import math

import numpy as np
import pytest
from PIL import Image

from monodbh.toolkit.evaluation.position_bench import _distance_m, exif_with_gps, true_tree_position


def _meta(yaw_deg, pitch_deg, bh_cam):
    """A camera looking along compass ``yaw_deg`` (world x east, y north, z up), pitched up."""
    y, p = math.radians(yaw_deg), math.radians(pitch_deg)
    fwd = np.array([math.sin(y) * math.cos(p), math.cos(y) * math.cos(p), math.sin(p)])
    right = np.array([math.cos(y), -math.sin(y), 0.0])
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd], axis=1)          # columns: camera x, y, z in the world
    return {"R_world_from_cam": R.tolist(), "roped_tree": 3,
            "trees": [{"id": 3, "bh_point_cam": list(bh_cam)}]}


def test_a_stem_ahead_and_to_the_right():
    # 4 m ahead, 3 m to the right, level camera facing the heading: bearing heading + 36.87 deg, 5 m
    lat, lon, horiz, bearing = true_tree_position(_meta(0.0, 0.0, [3.0, 0.2, 4.0]), 46.5, 6.6, 80.0)
    assert horiz == pytest.approx(5.0) and bearing == pytest.approx(80.0 + math.degrees(math.atan2(3, 4)))
    assert _distance_m(46.5, 6.6, lat, lon) == pytest.approx(5.0, abs=1e-3)


def test_pitch_changes_the_horizontal_distance_not_the_bearing_of_a_centred_stem():
    # the stem straight ahead of a camera pitched 20 deg up, 6 m along the optical axis
    *_, horiz, bearing = true_tree_position(_meta(30.0, 20.0, [0.0, 0.0, 6.0]), 10.0, 20.0, 123.0)
    assert horiz == pytest.approx(6.0 * math.cos(math.radians(20.0))) and bearing == pytest.approx(123.0)


def test_no_roped_tree():
    assert true_tree_position({"R_world_from_cam": np.eye(3).tolist(), "roped_tree": None, "trees": []},
                              0, 0, 0) is None


def test_exif_reads_back_as_the_pipeline_reads_it(tmp_path):
    from monodbh.toolkit.photo_meta import read_photo_meta

    p = tmp_path / "p.jpg"
    Image.new("RGB", (32, 24)).save(p, exif=exif_with_gps(-33.91234, 151.20123, 359.5))
    m = read_photo_meta(str(p))
    assert m.lat_deg == pytest.approx(-33.91234, abs=1e-7)
    assert m.lon_deg == pytest.approx(151.20123, abs=1e-7)
    assert m.heading_deg == pytest.approx(359.5) and m.heading_ref == "T"
