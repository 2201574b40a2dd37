"""The up direction and the stem's direction (toolkit.geometry.up)."""
from types import SimpleNamespace

import numpy as np
import pytest

from monodbh.toolkit.geometry import TrunkEdges, UpConfig
from monodbh.toolkit.geometry.up import choose_up, stem_axis
from monodbh.toolkit.result import MeasureResult


def test_stem_image_direction_blends_the_vertical():
    from types import SimpleNamespace

    from monodbh.toolkit.geometry.up import stem_image_direction

    STEM_DIRECTION_EDGE_WEIGHT = UpConfig().stem_direction_edge_weight

    cam = SimpleNamespace(K=np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]))
    tilted = np.array([np.sin(np.radians(10)), np.cos(np.radians(10))])
    # a level camera: the vertical through any pixel is the image column
    d = stem_image_direction(cam, (100.0, 300.0), tilted, {"vanishing": np.array([0.0, -1.0, 0.0])})
    ang = np.degrees(np.arctan2(d[0], d[1]))
    assert ang == pytest.approx(np.degrees(np.arctan2(STEM_DIRECTION_EDGE_WEIGHT * tilted[0],
                                                      STEM_DIRECTION_EDGE_WEIGHT * tilted[1]
                                                      + 1 - STEM_DIRECTION_EDGE_WEIGHT)), abs=1e-6)
    # no pose and no vanishing point: the edges' own direction
    assert np.allclose(stem_image_direction(cam, (100.0, 300.0), tilted, {"ground_plane": np.zeros(3)}), tilted)


def test_stem_image_direction_weight_comes_from_the_config():
    from monodbh.toolkit.geometry.up import stem_image_direction

    cam = SimpleNamespace(K=np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]))
    tilted = np.array([np.sin(np.radians(10)), np.cos(np.radians(10))])
    up = {"pose": np.array([0.0, -1.0, 0.0])}
    # all weight on the edges: their own direction; none: the image column of the vertical
    assert np.allclose(stem_image_direction(cam, (100.0, 300.0), tilted, up, UpConfig(stem_direction_edge_weight=1.0)),
                       tilted)
    assert np.allclose(stem_image_direction(cam, (100.0, 300.0), tilted, up, UpConfig(stem_direction_edge_weight=0.0)),
                       [0.0, 1.0])


def test_up_follows_the_priority_and_falls_back_to_the_image():
    pose, vp = np.array([0.0, -1.0, 0.0]), np.array([0.1, 0.99, 0.0])      # (the vanishing up points down: flipped)
    flags, res = [], MeasureResult(photo="")
    assert np.array_equal(choose_up({"pose": pose, "vanishing": vp}, flags, res), pose)
    assert res.debug["up_source"] == "pose" and set(res.debug["up_sources"]) == {"pose", "vanishing"}
    res = MeasureResult(photo="")
    up = choose_up({"pose": pose, "vanishing": vp}, flags, res, UpConfig(priority=("vanishing", "pose")))
    assert np.array_equal(up, -vp) and res.debug["up_source"] == "vanishing"
    assert flags == []
    sources = {}
    assert np.array_equal(choose_up(sources, flags, MeasureResult(photo="")), [0.0, -1.0, 0.0])
    assert flags == ["up_from_image"] and "image" in sources


def test_stem_axis_of_a_vertical_stem_straight_ahead():
    """A level pinhole camera, a vertical stem of radius 0.15 m at 5 m straight ahead: the stem
    direction is up, the axis ray goes through the stem's centre, sin(alpha / 2) = r / D."""
    from monodbh.calib import Camera
    f, r, D = 500.0, 0.15, 5.0
    cam = Camera(np.array([[f, 0, 320], [0, f, 240], [0, 0, 1]]), None, (640, 480))
    half = f * np.tan(np.arcsin(r / D))                  # the tangent rays' image offsets
    edges = TrunkEdges(left_xy=np.array([320 - half, 240.0]), right_xy=np.array([320 + half, 240.0]),
                       width_px=2 * half, along=np.array([0.0, 1.0]), across=np.array([1.0, 0.0]))
    ax = stem_axis(cam, edges, np.array([0.0, -1.0, 0.0]))
    np.testing.assert_allclose(ax.v, [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(ax.r_A, [0, 0, 1], atol=1e-12)
    assert ax.sin_half == pytest.approx(r / D, rel=1e-9)
