"""The rope finder's runtime: tiling, candidates, the knot band, the shipped model."""
import numpy as np
import pytest

from monodbh.models.runtime.rope_finder import TILE, RopeFinderConfig, knot_band, rope_components, tile_origins


def _roped_photo(h=480, w=640, row=250, rope_rgb=(170, 40, 35), x0=300, x1=341):
    """A brown vertical stem (x0-x1) on a green background with a thin red rope across it."""
    rng = np.random.default_rng(0)
    img = np.full((h, w, 3), (90, 120, 80), np.float64) + rng.normal(0, 3, (h, w, 3))
    img[:, x0:x1] = (105, 90, 75)
    rope = np.zeros((h, w), bool)
    if rope_rgb is not None:
        img[row:row + 2, x0:x1] = rope_rgb
        rope[row:row + 2, x0:x1] = True
    inst = np.zeros((h, w), np.uint16)
    inst[:, x0:x1] = 1
    return np.clip(img, 0, 255).astype(np.uint8), rope, inst


def test_tile_origins_cover_with_overlap():
    BORDER = RopeFinderConfig().border_px
    for size in (100, 384, 385, 500, 960, 1280, 1601):
        xs = tile_origins(size)
        assert xs[0] == 0 and all(x % 2 == 0 for x in xs)
        # the kept middles (BORDER left out where a neighbour covers it) leave no gap
        kept_end = TILE if len(xs) > 1 else size
        for a, b in zip(xs, xs[1:]):
            assert b + BORDER <= a + TILE - BORDER
        assert xs[-1] + TILE >= size - 1 and kept_end > 0


def test_rope_components_line_merge_and_blob():
    z = np.full((100, 150), -8.0, np.float32)
    z[40, 20:50] = 5.0
    z[41, 56:80] = 5.0                 # the same rope behind a twig: merged
    z[80:90, 100:110] = 5.0            # a blob
    comps = rope_components(z)
    assert len(comps) == 2
    blob, line = comps                 # best mass first
    assert line.n == 30 + 24 and line.length_px > 110 and abs(line.direction[1]) < 0.05
    assert line.thickness_px < 3 and blob.n == 100 and blob.length_px < 3 * blob.thickness_px
    assert rope_components(np.full((10, 10), -5.0, np.float32)) == []
    with pytest.raises(ValueError):
        rope_components(np.zeros((2, 3, 4)))


def test_rope_components_follow_their_config():
    """The candidates' rules are the config's: a stricter merge keeps the twig-broken rope in two
    pieces, a smaller blob limit drops the blob, a higher log-odds floor sees nothing."""
    z = np.full((100, 150), -8.0, np.float32)
    z[40, 20:50] = 5.0
    z[41, 56:80] = 5.0
    z[80:90, 100:110] = 5.0
    assert len(rope_components(z, config=RopeFinderConfig(merge_gap_cells=0.0, merge_reach=0.1))) == 3
    only_lines = rope_components(z, config=RopeFinderConfig(max_piece_cells=100))
    assert len(only_lines) == 1 and only_lines[0].n == 54
    assert rope_components(z, config=RopeFinderConfig(logit_lo=6.0)) == []
    assert len(rope_components(z, config=RopeFinderConfig(max_components=1))) == 1


def _shipped_finder():
    from monodbh.models.runtime import load_manifest
    from monodbh.models.runtime.rope_finder import RopeFinder

    if "rope_finder" not in load_manifest().get("models", {}):
        pytest.skip("no shipped rope finder")
    return RopeFinder(threads=1)


def test_shipped_rope_finder_finds_a_rope_and_nothing_without_one():
    from monodbh.toolkit.rope.finder import rope_from_finder

    finder = _shipped_finder()
    img, rope, _ = _roped_photo()
    z = finder.logit_map(img)
    assert z.shape == (240, 320) and z.dtype == np.float32
    det = rope_from_finder(rope_components(z), img.shape[:2])
    assert det, det.reason
    assert abs(det.center_xy[1] - 250.5) <= 3 and 295 <= det.center_xy[0] <= 346
    assert det.polyline[0, 0] < 306 and det.polyline[-1, 0] > 335      # spans the stem
    img0, _, _ = _roped_photo(rope_rgb=None)
    assert not rope_from_finder(finder.components(img0), img0.shape[:2])
    with pytest.raises(ValueError):
        finder.logit_map(img.astype(np.float32))


def test_knot_band_without_a_near_horizontal_line():
    """A piece with no near-horizontal line (a vertical paint mark) has no band; with OpenCV 5,
    ``cv2.HoughLines`` returns an empty array there instead of None (was an IndexError)."""
    ys, xs = np.arange(40), np.full(40, 7)
    assert knot_band(ys, xs) is None
    ys = np.r_[np.full(30, 10), np.arange(11, 25)]
    xs = np.r_[np.arange(30), np.full(14, 20)]
    assert knot_band(ys, xs)[:30].all()
    # a band tilted 30 degrees is found within the default 40 degrees, not within 20
    t = np.arange(40)
    ys, xs = np.round(10 + t * np.tan(np.radians(30))).astype(int), t
    assert knot_band(ys, xs) is not None
    assert knot_band(ys, xs, RopeFinderConfig(knot_max_tilt_deg=20.0)) is None
