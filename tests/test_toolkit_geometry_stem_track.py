"""The edge tracker following the stem down to its base (toolkit.geometry.stem_track)."""
import numpy as np

from monodbh.toolkit.geometry import trunk_edges
from geometry_scenes import paint_stem


def _scene(bush: bool = False, W=480, H=640, x0=200.0, x1=260.0, y_base=560):
    """A stem standing on the ground: sky-grey background above the horizon (y 300), brown
    ground below, the stem (x0..x1) from the top down to ``y_base``; optionally a green bush
    hiding the stem's lowest 120 px. Returns rgb, gray, tree and ground masks."""
    rng = np.random.default_rng(0)
    rgb = paint_stem(W, H, x0, x1, y_base)
    if bush:
        yy, xx = np.mgrid[0:H, 0:W]
        m = ((xx - 230) / 90.0) ** 2 + ((yy - y_base + 30) / 90.0) ** 2 < 1
        rgb[m] = (40, 110, 35)
    rgb = np.clip(rgb + rng.normal(0, 2.0, rgb.shape), 0, 255).astype(np.uint8)
    tree = np.zeros((H, W), bool)
    tree[:y_base, int(x0) + 2:int(x1) - 2] = True
    ground = np.zeros((H, W), bool)
    ground[300:] = True
    ground &= ~tree
    if bush:
        ground[m] = False
    return rgb, rgb.astype(np.float32).mean(2), tree, ground


def test_stem_base_is_found_where_the_edges_meet_the_ground():
    from monodbh.toolkit.geometry import track_stem_base
    rgb, gray, tree, ground = _scene()
    e = trunk_edges(gray, tree, (230.0, 250.0), (1.0, 0.0), rope_half_px=2.0, search_px=6.0)
    assert e, e.reason
    base, status, info = track_stem_base(gray, e, ground, tree, rgb=rgb, rope_half_px=2.0)
    assert status == "ground"
    assert abs(base[0] - 230.0) < 1.5 and abs(base[1] - 559.5) < 1.5


def test_stem_base_hidden_by_a_bush_is_not_reported():
    from monodbh.toolkit.geometry import track_stem_base
    rgb, gray, tree, ground = _scene(bush=True)
    e = trunk_edges(gray, tree, (230.0, 250.0), (1.0, 0.0), rope_half_px=2.0, search_px=6.0)
    base, status, info = track_stem_base(gray, e, ground, tree, rgb=rgb, rope_half_px=2.0)
    assert base is None and status in ("occluded", "off_mask")
