"""Trunk silhouette edges at the rope (toolkit.edges.trunk_edges)."""
import numpy as np

from monodbh.toolkit.edges import trunk_edges


def _stem_image(x0, x1, W=640, H=480, bg=60.0, bark=170.0):
    """A vertical stem between x0 and x1 (sub-pixel, anti-aliased; pixel centres at integer
    coordinates, as in OpenCV), (H, W) float32."""
    xs = np.arange(W, dtype=np.float64)
    cover = np.clip(np.minimum(xs - x0, x1 - xs) + 0.5, 0, 1)
    row = bg + (bark - bg) * cover
    return np.tile(row.astype(np.float32), (H, 1))


def test_wide_stem_at_the_photo_border_is_found():
    # a close stem 300 px wide whose sampling lines leave the photo on the left, beyond the stem
    x0, x1 = 20.3, 320.7
    gray = _stem_image(x0, x1)
    mask = np.zeros(gray.shape, bool)
    mask[:, 24:318] = True            # a coarse mask, a few pixels inside the true borders
    e = trunk_edges(gray, mask, (170.0, 240.0), (1.0, 0.0), rope_half_px=3.0, search_px=6.0)
    assert e, e.reason
    assert abs(e.left_xy[0] - x0) < 0.3 and abs(e.right_xy[0] - x1) < 0.3


def test_stem_leaving_the_photo_says_so():
    gray = _stem_image(-50.0, 250.0)
    mask = np.zeros(gray.shape, bool)
    mask[:, 0:248] = True
    e = trunk_edges(gray, mask, (100.0, 240.0), (1.0, 0.0), rope_half_px=3.0, search_px=6.0)
    assert not e
    assert "runs out of the photo" in e.reason


def _scene(bush: bool = False, W=480, H=640, x0=200.0, x1=260.0, y_base=560):
    """A stem standing on the ground: sky-grey background above the horizon (y 300), brown
    ground below, the stem (x0..x1) from the top down to ``y_base``; optionally a green bush
    hiding the stem's lowest 120 px. Returns rgb, gray, tree and ground masks."""
    rng = np.random.default_rng(0)
    rgb = np.zeros((H, W, 3), np.float32)
    rgb[:300] = (150, 160, 170)
    rgb[300:] = (120, 95, 60)
    xs = np.arange(W, dtype=np.float64)
    cover = np.clip(np.minimum(xs - x0, x1 - xs) + 0.5, 0, 1)[None, :, None]
    stem = np.zeros((H, 1, 1))
    stem[:y_base] = 1.0
    bark = np.array([70.0, 60.0, 55.0])
    rgb = rgb * (1 - cover * stem) + bark * cover * stem
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
    from monodbh.toolkit.edges import track_stem_base
    rgb, gray, tree, ground = _scene()
    e = trunk_edges(gray, tree, (230.0, 250.0), (1.0, 0.0), rope_half_px=2.0, search_px=6.0)
    assert e, e.reason
    base, status, info = track_stem_base(gray, e, ground, tree, rgb=rgb, rope_half_px=2.0)
    assert status == "ground"
    assert abs(base[0] - 230.0) < 1.5 and abs(base[1] - 559.5) < 1.5


def test_stem_base_hidden_by_a_bush_is_not_reported():
    from monodbh.toolkit.edges import track_stem_base
    rgb, gray, tree, ground = _scene(bush=True)
    e = trunk_edges(gray, tree, (230.0, 250.0), (1.0, 0.0), rope_half_px=2.0, search_px=6.0)
    base, status, info = track_stem_base(gray, e, ground, tree, rgb=rgb, rope_half_px=2.0)
    assert base is None and status in ("occluded", "off_mask")
