"""Pieces, links, runs and the band fit of the band detector (monodbh.toolkit.rope.band_segments)."""
import numpy as np

from monodbh.toolkit.rope.band_segments import band_runs, fit_band, line_pieces, link_pieces, piece_ends
from monodbh.toolkit.rope.redness import line_contrast, redness_map


def _pieces(img):
    F = redness_map(img)
    R = line_contrast(F)
    return piece_ends(line_pieces(R, F, img, thr=0.012, min_len=5.0, level=0))


def test_a_band_broken_by_an_occluder_is_linked_and_fitted_as_one():
    img = np.full((200, 300, 3), (95, 75, 55), np.uint8)
    img[100:103, 40:120] = (170, 25, 20)
    img[100:103, 140:220] = (170, 25, 20)        # the same rope behind a thin stem (x 120-140)
    img[40:43, 150:200] = (170, 25, 20)          # another band, far above
    seg = _pieces(img)
    assert len(seg["cx"]) == 3
    chains = link_pieces(seg)
    assert sorted(len(ch) for ch in chains) == [1, 2]
    runs = band_runs(seg, chains, min_contrast=0.015)
    two = next(r for r in runs if len(r) == 2)
    fit = fit_band(seg, two)
    assert fit.members == 2 and abs(fit.center_xy[1] - 101.0) < 0.5 and abs(fit.direction[1]) < 0.01
    assert 170 < fit.length_px < 190 and fit.coverage < 1.0
    assert fit.polyline.shape == (24, 2) and fit.polyline.dtype == np.float32


def test_vertical_marks_make_no_pieces():
    img = np.full((200, 300, 3), (95, 75, 55), np.uint8)
    img[40:160, 100:103] = (170, 25, 20)         # a vertical paint mark
    F = redness_map(img)
    assert line_pieces(line_contrast(F), F, img, thr=0.012, min_len=5.0, level=0) is None
