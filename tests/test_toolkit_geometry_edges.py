"""Trunk silhouette edges at the rope (toolkit.geometry.edges): trunk_edges, rope_row_contrast, channel_mean."""
import numpy as np

from monodbh.toolkit.geometry import trunk_edges
from geometry_scenes import roped_pair


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


def test_rope_row_contrast_is_high_on_the_rope_only():
    from monodbh.toolkit.geometry import rope_row_contrast
    from monodbh.toolkit.rope import redness_map
    rgb, _ = roped_pair(rope_to=260)
    F = redness_map(rgb)
    s = np.arange(-100.0, 100.0, 1.0)          # from x 130 to 330 across the rope at (230, 200)
    c = rope_row_contrast(F, (230.0, 200.0), (1.0, 0.0), (1.0, 0.0), (0.0, 1.0), s, rope_half_px=2.5)
    on_rope = (s > -25) & (s < 25)
    on_neighbour = (s > 35) & (s < 95)
    assert c[on_rope].min() > 0.2
    assert np.abs(c[on_neighbour]).max() < 0.02


def test_channel_mean_is_numpys_mean_bit_for_bit():
    from monodbh.toolkit.geometry import channel_mean

    rng = np.random.default_rng(5)
    for shape in [(37, 53, 3), (1, 1, 3), (200, 300, 3)]:
        rgb = rng.integers(0, 256, shape, dtype=np.uint8)
        got = channel_mean(rgb)
        assert got.dtype == np.float32 and np.array_equal(got, rgb.astype(np.float32).mean(2))


def test_refit_edges_moves_a_side_onto_its_kept_points():
    from monodbh.toolkit.geometry.edges import TrunkEdges, refit_edges
    # a vertical stem x 100..160 whose right side has 4 stray points 6 px outside, below the rope
    t = np.array([-20.0, -15, -10, -5, 5, 10, 15, 20])
    left = np.c_[np.full(8, 100.0), 200 + t]
    right = np.c_[np.r_[np.full(4, 160.0), np.full(4, 166.0)], 200 + t]
    e = TrunkEdges(left_xy=np.array([100.0, 200]), right_xy=np.array([163.0, 200]), width_px=63.0,
                   along=np.array([0.0, 1.0]), across=np.array([1.0, 0.0]), edge_rms_px=3.0, n_lines=8,
                   points=dict(left=left, right=right))
    keep = {"right": np.r_[np.ones(4, bool), np.zeros(4, bool)]}
    r = refit_edges(e, keep)
    assert abs(r.left_xy[0] - 100.0) < 1e-6 and abs(r.right_xy[0] - 160.0) < 1e-6
    assert abs(r.width_px - 60.0) < 1e-6 and abs(r.along[0]) < 1e-6 and len(r.points["right"]) == 4
    # fewer than 3 points left on a side: the edges as they were
    assert refit_edges(e, {"right": np.r_[np.ones(2, bool), np.zeros(6, bool)]}) is e


def test_combine_edges_puts_both_sides_on_the_frames_cross_section():
    from monodbh.toolkit.geometry.edges import TrunkEdges, combine_edges
    # a vertical stem x 100..160 at the rope row y 200; the left side was found on a line through
    # another centre (y 230) with a tilted cross-section: its point lies 30 px lower on x 100
    frame = TrunkEdges(left_xy=np.array([102.0, 200]), right_xy=np.array([160.0, 200]), width_px=58.0,
                       along=np.array([0.0, 1.0]), across=np.array([1.0, 0.0]), edge_rms_px=0.5, n_lines=8,
                       points=dict(left=np.zeros((0, 2)), right=np.zeros((0, 2))))
    other = TrunkEdges(left_xy=np.array([100.0, 230]), right_xy=np.array([170.0, 250]), width_px=72.0,
                       along=np.array([0.0, 1.0]), across=np.array([0.96, 0.28]), edge_rms_px=0.5, n_lines=8,
                       points=dict(left=np.zeros((0, 2)), right=np.zeros((0, 2))))
    e = combine_edges(other, frame, frame=frame)
    np.testing.assert_allclose(e.left_xy, [100.0, 200.0], atol=1e-9)
    np.testing.assert_allclose(e.right_xy, [160.0, 200.0], atol=1e-9)
    assert abs(e.width_px - 60.0) < 1e-9
    # a side line parallel to the cross-section (no crossing): its point stays
    flat = TrunkEdges(left_xy=np.array([90.0, 210]), right_xy=np.array([170.0, 210]), width_px=80.0,
                      along=np.array([1.0, 0.0]), across=np.array([0.0, 1.0]), edge_rms_px=0.5, n_lines=8,
                      points=dict(left=np.zeros((0, 2)), right=np.zeros((0, 2))))
    np.testing.assert_allclose(combine_edges(flat, frame, frame=frame).left_xy, [90.0, 210.0])
