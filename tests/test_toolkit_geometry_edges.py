"""Trunk silhouette edges at the rope (toolkit.edges.trunk_edges)."""
import numpy as np
import pytest

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


def _paint_stem(W, H, x0, x1, y_base):
    """(H, W, 3) float32: sky grey above row 300, brown ground below, a bark-coloured stem
    between x0 and x1 (anti-aliased) from the top down to ``y_base``."""
    rgb = np.zeros((H, W, 3), np.float32)
    rgb[:300] = (150, 160, 170)
    rgb[300:] = (120, 95, 60)
    xs = np.arange(W, dtype=np.float64)
    cover = np.clip(np.minimum(xs - x0, x1 - xs) + 0.5, 0, 1)[None, :, None]
    stem = np.zeros((H, 1, 1))
    stem[:y_base] = 1.0
    return rgb * (1 - cover * stem) + np.array([70.0, 60.0, 55.0]) * cover * stem


def _scene(bush: bool = False, W=480, H=640, x0=200.0, x1=260.0, y_base=560):
    """A stem standing on the ground: sky-grey background above the horizon (y 300), brown
    ground below, the stem (x0..x1) from the top down to ``y_base``; optionally a green bush
    hiding the stem's lowest 120 px. Returns rgb, gray, tree and ground masks."""
    rng = np.random.default_rng(0)
    rgb = _paint_stem(W, H, x0, x1, y_base)
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


def _level_scene(bush: bool):
    """A level pinhole camera 1.5 m above flat ground (f 500 px, horizon at row 300) looking at
    a 0.3 m stem 5 m away: rope (1.3 m) at row 320, base at row 450; the bush hides the stem
    below 0.4 m (row 410)."""
    from monodbh.calib import Camera
    f, cx, cy, Z, h = 500.0, 240.0, 300.0, 5.0, 1.5
    W, H = 480, 640
    x0, x1 = cx - 0.5 * f * 0.3 / Z, cx + 0.5 * f * 0.3 / Z
    rgb = _paint_stem(W, H, x0, x1, 450)
    yy, xx = np.mgrid[0:H, 0:W]
    tree = np.zeros((H, W), bool)
    tree[:450, int(x0) + 2:int(x1) - 1] = True
    if bush:
        m = ((xx - cx) / 60.0) ** 2 + ((yy - 455) / 45.0) ** 2 < 1
        rgb[m] = (40, 110, 35)
        tree &= ~m
    rgb = np.clip(rgb + np.random.default_rng(0).normal(0, 2.0, rgb.shape), 0, 255).astype(np.uint8)
    ground = (yy >= 300) & ~tree
    if bush:
        ground &= ~m
    rgb[318:322, int(x0):int(x1) + 1] = (200, 30, 30)            # the rope
    depth = np.where(tree, 1.7 * Z, 0.0).astype(np.float32)       # a network 70 % too far
    # (and no depth on the ground: no ground plane, the camera is taken as level)
    cam = Camera(np.array([[f, 0, cx], [0, f, cy], [0, 0, 1]]), None, (W, H))
    return rgb, tree, ground, depth, cam


def test_stem_hidden_by_a_bush_caps_a_too_far_network_scale():
    """The base is at or below where a bush hides the stem: a network distance beyond the
    metrology through that point is capped to it (5 m true; 8.5 m network; bound 5 x 1.3 / 0.9)."""
    from monodbh.toolkit.measure_core import Perception, measure_from_perception
    for bush in (True, False):
        rgb, tree, ground, depth, cam = _level_scene(bush)
        p = Perception(rgb=rgb, camera=cam, rope_xy=np.array([240.0, 320.0]), rope_dir=np.array([1.0, 0.0]),
                       rope_half_px=2.0, tree_mask=tree, ground_mask=ground, depth=depth,
                       source="network", use_vanishing=False,
                       sigma_network={"network": 0.37, "stem_base": 0.05})
        r = measure_from_perception(p)
        assert r.error is None, r.error
        if bush:
            assert "scale_capped_by_visible_stem" in r.flags
            assert r.scale_source.startswith("visible_stem+network")
            assert 6.9 < r.distance_m < 7.6                       # not 8.8: capped near 7.3
        else:                                                     # the base itself is seen
            assert r.scale_source.startswith("stem_base"), r.scale_source
            assert r.distance_m == pytest.approx(5.15, rel=0.03)    # to the axis: 5 m + radius
            assert "scale_capped_by_visible_stem" not in r.flags
    # a distance calibration (error model) applies to network-led scales only, before the cap
    rgb, tree, ground, depth, cam = _level_scene(False)
    kw = dict(rgb=rgb, camera=cam, rope_xy=np.array([240.0, 320.0]), rope_dir=np.array([1.0, 0.0]),
              rope_half_px=2.0, tree_mask=tree, ground_mask=np.zeros_like(ground), depth=depth,
              source="network", use_vanishing=False)
    r0 = measure_from_perception(Perception(**kw))
    r1 = measure_from_perception(Perception(**kw, distance_calibration={"a": 0.0, "b": 0.7}))
    assert "distance_calibrated" in r1.flags and r1.scale_source == "network"
    lam0 = r0.debug["lam_combined"]                     # 8.8 m: capped to 5.2 without calibration
    assert r1.debug["lam_uncalibrated"] == pytest.approx(lam0)
    lam1 = np.exp(0.7 * np.log(lam0))                   # 4.6 m: below the bound, not capped
    assert np.linalg.norm(r1.debug["axis_point"]) == pytest.approx(lam1, rel=1e-6)
    assert r1.dbh_cm / r0.dbh_cm == pytest.approx(lam1 / np.linalg.norm(r0.debug["axis_point"]), rel=2e-3)
    # the calibrated distances' own measured spread replaces the raw network's sigma
    r2 = measure_from_perception(Perception(**kw, distance_calibration={"a": 0.0, "b": 0.7, "sigma": 0.2}))
    assert r2.dbh_cm == pytest.approx(r1.dbh_cm)
    assert r2.dbh_sigma_cm / r2.dbh_cm < r1.dbh_sigma_cm / r1.dbh_cm
    assert r2.dbh_sigma_cm / r2.dbh_cm == pytest.approx(0.2, abs=0.05)


def _roped_pair(rope_to: float, shade_from: float | None = None, W=480, H=400):
    """Grey background, the roped stem (x 200..260, brown bark) and a lighter neighbouring trunk
    behind it (x 260..330); a red rope (rows 198..202) painted from x 200 to ``rope_to``; with
    ``shade_from``, the roped stem (and its rope) darker from there on. Returns rgb (H, W, 3)
    uint8 and the coarse mask the segmenter gives for both trunks together."""
    rng = np.random.default_rng(1)
    rgb = np.zeros((H, W, 3), np.float32)
    rgb[:] = (150, 160, 170)
    rgb[:, 260:330] = (175, 165, 140)
    rgb[:, 200:260] = (90, 70, 55)
    rgb[198:203, 200:int(rope_to)] = (170, 30, 25)
    if shade_from is not None:
        rgb[:, int(shade_from):260] *= 0.55
    rgb = np.clip(rgb + rng.normal(0, 2.0, rgb.shape), 0, 255).astype(np.uint8)
    mask = np.zeros((H, W), bool)
    mask[:, 198:332] = True
    return rgb, mask


def _perception(rgb, mask, band_x0, band_x1):
    from monodbh.toolkit.measure_core import Perception
    band = np.zeros(mask.shape, bool)
    L = band_x1 - band_x0
    band[200 - L:200 + L + 1, band_x0:band_x1] = True      # as the pipeline's: the rope's length above and below
    return Perception(rgb=rgb, camera=None, rope_xy=np.array([0.5 * (band_x0 + band_x1), 200.0]),
                      rope_dir=np.array([1.0, 0.0]), rope_half_px=2.5, tree_mask=mask,
                      ground_mask=np.zeros_like(mask), edge_search_px=6.0, rope_band_mask=band,
                      rope_length_px=float(band_x1 - band_x0))


def test_rope_row_contrast_is_high_on_the_rope_only():
    from monodbh.toolkit.edges import rope_row_contrast
    from monodbh.toolkit.rope import redness_map
    rgb, _ = _roped_pair(rope_to=260)
    F = redness_map(rgb)
    s = np.arange(-100.0, 100.0, 1.0)          # from x 130 to 330 across the rope at (230, 200)
    c = rope_row_contrast(F, (230.0, 200.0), (1.0, 0.0), (1.0, 0.0), (0.0, 1.0), s, rope_half_px=2.5)
    on_rope = (s > -25) & (s < 25)
    on_neighbour = (s > 35) & (s < 95)
    assert c[on_rope].min() > 0.2
    assert np.abs(c[on_neighbour]).max() < 0.02


def test_merged_neighbour_is_cut_at_the_rope_end():
    # the mask took in the neighbouring trunk on the right: the rope ends at the roped stem's
    # edge, so that side's edge is searched there; the left side stays
    from monodbh.toolkit.measure_core import _edges_checked_by_rope, _edges_two_pass
    rgb, mask = _roped_pair(rope_to=260)
    perc = _perception(rgb, mask, 201, 259)
    gray = rgb.astype(np.float32).mean(2)
    e1 = _edges_two_pass(gray, mask, perc)
    assert e1 and e1.right_xy[0] > 320          # the mask-guided pair spans both trunks
    e, n = _edges_checked_by_rope(gray, perc, e1)
    assert n == 1
    assert abs(e.left_xy[0] - 199.5) < 1.0 and abs(e.right_xy[0] - 259.5) < 1.0
    assert abs(e.width_px - 60.0) < 1.5


def test_rope_seen_on_part_of_the_stem_keeps_the_mask_edge():
    # the rope goes on, darker, into the stem's shade beyond where the rope band was found:
    # the mask's edge is the stem's
    from monodbh.toolkit.measure_core import _edges_checked_by_rope, _edges_two_pass
    rgb, mask = _roped_pair(rope_to=260, shade_from=235)
    mask[:, 262:] = False                       # the mask is the roped stem's only
    perc = _perception(rgb, mask, 201, 235)
    gray = rgb.astype(np.float32).mean(2)
    e1 = _edges_two_pass(gray, mask, perc)
    e, n = _edges_checked_by_rope(gray, perc, e1)
    assert n == 0
    assert abs(e.right_xy[0] - 259.5) < 1.0


def test_channel_mean_is_numpys_mean_bit_for_bit():
    from monodbh.toolkit.measure_core import channel_mean

    rng = np.random.default_rng(5)
    for shape in [(37, 53, 3), (1, 1, 3), (200, 300, 3)]:
        rgb = rng.integers(0, 256, shape, dtype=np.uint8)
        got = channel_mean(rgb)
        assert got.dtype == np.float32 and np.array_equal(got, rgb.astype(np.float32).mean(2))
