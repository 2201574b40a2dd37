"""The stem-base network's runtime: strip geometry, strip cutting, decoding, the shipped model."""
import numpy as np
import pytest

from monodbh.models.runtime.stem_base import (STRIP_H, STRIP_ROWS_PER_W, STRIP_W, decode_base_logits,
                                              stem_strip, strip_geometry, strip_row_to_xy)


def test_strip_geometry_maps_rows_down_the_stem():
    A = strip_geometry((100.0, 50.0), (0.0, 2.0), 20.0)
    mid = A @ np.array([STRIP_W / 2 - 0.5, 0.0, 1.0])
    assert np.allclose(mid, (100, 50))
    down = A @ np.array([STRIP_W / 2 - 0.5, STRIP_ROWS_PER_W, 1.0])
    assert np.allclose(down, (100, 70))                      # 10 rows = one stem width
    assert np.allclose(strip_row_to_xy(5.0, (100, 50), (0, 1), 20.0), (100, 60))
    with pytest.raises(ValueError):
        strip_geometry((0, 0), (0, 0), 10.0)


def test_stem_strip_shape_inside_flag_and_content():
    rgb = np.zeros((200, 100, 3), np.uint8)
    rgb[:, 45:55] = 200                                       # a bright vertical stem, 10 px wide
    s, inside = stem_strip(rgb, (49.5, 20.0), (0, 1), 10.0)
    assert s.shape == (STRIP_H, STRIP_W, 3) and inside.shape == (STRIP_H, STRIP_W)
    # the strip is 19.2 widths long: it leaves the photo after 180 px (row 180)
    assert inside[:170].all() and not inside[185:].any()
    row = s[50, :, 0].astype(float)
    assert row[STRIP_W // 2] > 150 and row[2] < 50 and row[-3] < 50    # stem in the middle quarter
    assert (row > 100).sum() == pytest.approx(STRIP_W / 4, abs=2)


def test_decode_base_logits():
    z = np.full(STRIP_H + 1, -30.0)
    z[80] = 4.0
    z[81] = 4.0
    row, p = decode_base_logits(z)
    assert row == pytest.approx(80.5) and p > 0.999
    z[-1] = 10.0
    assert decode_base_logits(z)[1] < 0.01


def test_shipped_stem_base_finder_on_the_bundled_example():
    from pathlib import Path

    import monodbh.toolkit.pipeline as pl
    from monodbh.calib.photo import load_photo
    from monodbh.models.runtime.stem_base import BaseEstimate, StemBaseFinder

    finder = StemBaseFinder()
    assert finder.spec["kind"] == "stem_base" and 0.0 < finder.threshold < 1.0
    rgb = load_photo(Path(pl.__file__).resolve().parent / "examples" / "example.jpg")
    H, W = rgb.shape[:2]
    z = finder.logits(rgb, (W / 2, H / 2), (0.0, 1.0), 30.0)
    assert z.shape == (STRIP_H + 1,) and np.isfinite(z).all()
    est = finder.find(rgb, (W / 2, H / 2), (0.0, 1.0), 30.0)
    assert isinstance(est, BaseEstimate) and 0.0 <= est.p_base <= 1.0
    assert (est.xy is None) == (est.p_base < finder.threshold)
    if est:
        assert est.xy[1] > H / 2 and abs(est.xy[0] - W / 2) < 1e-6   # on the strip's mid-line, below


def test_the_second_network_is_asked_only_where_the_first_sees_no_base():
    from monodbh.models.runtime import load_networks
    from monodbh.models.runtime.stem_base import BaseEstimate, StemBaseFinder, StemBaseNetFinder

    second = StemBaseNetFinder()
    assert second.spec["kind"] == "stem_base_net" and second.spec["inputs"] == StemBaseFinder().spec["inputs"]
    first = StemBaseFinder(second=second)
    rgb = np.zeros((64, 64, 3), np.uint8)
    assert second.find(rgb, (32, 10), (0, 1), 8.0).network == "stem_base_net"    # the result says who read it
    assert first._find(rgb, (32, 10), (0, 1), 8.0).network == "stem_base"
    none = BaseEstimate(None, 0.2, 50.0, "none")
    found = BaseEstimate(np.array([10.0, 40.0]), 0.8, 30.0, "found")
    first._find = lambda *a: found
    second.find = lambda *a: (_ for _ in ()).throw(AssertionError("asked although the first found a base"))
    assert first.find(rgb, (32, 10), (0, 1), 8.0) is found
    first._find = lambda *a: none
    second.find = lambda *a: found
    assert first.find(rgb, (32, 10), (0, 1), 8.0) is found
    second.find = lambda *a: BaseEstimate(None, 0.4, 20.0, "none")
    assert first.find(rgb, (32, 10), (0, 1), 8.0) is none      # neither: the first's answer
    nets = load_networks(threads=1)
    assert isinstance(nets.stem_base.second, StemBaseNetFinder)
