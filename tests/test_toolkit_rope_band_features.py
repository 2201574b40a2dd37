"""The band detector's candidate features and score (monodbh.toolkit.rope.band_features)."""
from dataclasses import replace

import cv2
import numpy as np

from monodbh.toolkit.rope.band_features import (BoxCounts, band_clutter, candidate_features, candidate_score,
                                                context_maps, band_context, red_area)
from monodbh.toolkit.rope.band_segments import BandFit
from monodbh.toolkit.rope.config import BandConfig
from monodbh.toolkit.rope.redness import line_contrast, redness_map


def test_box_counts_on_the_cell_grid_equal_summed_cells():
    """BoxCounts samples the pixel integral at the cell corners (speed): the values must be those
    of summing each cell first."""
    rng = np.random.default_rng(3)
    rng.integers(0, 256, (61, 83, 3), dtype=np.uint8)
    mask = rng.random((61, 83)) < 0.2
    for cell in (4, 3):
        hc, wc = -(-61 // cell), -(-83 // cell)
        m = np.zeros((hc * cell, wc * cell), np.float32)
        m[:61, :83] = mask
        cnt = m.reshape(hc, cell, wc, cell).sum((1, 3))
        assert np.array_equal(BoxCounts(mask, cell).I, cv2.integral(cnt, sdepth=cv2.CV_64F))


def _fit(x0=100.0, x1=180.0, y=120.0, thick=3.0, **kw):
    xs = np.linspace(x0, x1, 24)
    poly = np.stack([xs, np.full_like(xs, y)], 1).astype(np.float32)
    return BandFit(center_xy=(0.5 * (x0 + x1), y), direction=(1.0, 0.0), length_px=x1 - x0 + 1.0,
                   thickness_px=thick, contrast=0.05, coverage=1.0, hue=0.1, red=0.2, polyline=poly, **kw)


def _photo():
    """A rope-red band (rows 119-121) across a brown trunk (x 100-180) on green."""
    img = np.full((240, 320, 3), (70, 110, 60), np.uint8)
    img[:, 100:181] = (95, 75, 55)
    img[119:122, 100:181] = (170, 25, 20)
    return img


def test_context_passes_are_pure_and_read_the_surroundings():
    img = _photo()
    F = redness_map(img)
    R = line_contrast(F)
    maps = context_maps(img, BoxCounts(R > 0.012), F, [R])
    fit = _fit()
    before = fit.polyline.copy()
    a, b = band_context(fit, maps), band_context(fit, maps)
    assert a == b and np.array_equal(fit.polyline, before)
    assert min(a.edges) > 0.5                # both ends on the trunk's silhouette
    assert a.red_area < 0.05 and a.clutter < 0.1
    # red all around the band (a jacket): its surroundings are as red as it
    jacket = img.copy()
    jacket[60:180, 60:220] = (170, 25, 20)
    assert red_area(fit, redness_map(jacket)) > 0.5
    assert band_clutter(fit, BoxCounts(np.ones((240, 320), bool)))[1] == 1.0


def test_score_gates_follow_the_config():
    """Too short for its thickness (``min_elongation``) or too orange (``max_hue``): -inf; a
    deep band ``deep_prior`` lower; else the linear score of its features."""
    img = _photo()
    F = redness_map(img)
    R = line_contrast(F)
    maps = context_maps(img, BoxCounts(R > 0.012), F, [R])
    fit = _fit()
    feats = candidate_features(fit, band_context(fit, maps))
    w = BandConfig().score_weights
    s = candidate_score(fit, feats, w)
    assert np.isfinite(s)
    assert candidate_score(replace(fit, deep=True), feats, w) == s - BandConfig().deep_prior
    stubby = replace(fit, thickness_px=20.0)                          # 81 px long, 20 thick: 4 x
    assert candidate_score(stubby, feats, w) == -np.inf
    assert np.isfinite(candidate_score(stubby, feats, w, replace(BandConfig(), min_elongation=3.0)))
    orange = replace(fit, hue=0.4)
    assert candidate_score(orange, feats, w) == -np.inf
    assert np.isfinite(candidate_score(orange, feats, w, replace(BandConfig(), max_hue=0.5)))
