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
