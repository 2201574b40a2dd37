"""The stem-edge network's runtime: patch geometry, patch cutting, decoding, the shipped model."""
import numpy as np
import pytest

from monodbh.models.runtime.stem_edge import (PATCH_COLS_PER_W, PATCH_H, PATCH_W, decode_edge_logits, edge_patch,
                                              patch_geometry)


def test_patch_geometry_columns_run_left_to_right_across_the_stem():
    A = patch_geometry((100.0, 50.0), (0.0, 2.0), 32.0)
    centre = A @ np.array([PATCH_W / 2 - 0.5, PATCH_H / 2 - 0.5, 1.0])
    assert np.allclose(centre, (100, 50))
    # one stem width = PATCH_COLS_PER_W columns, to the right in the photo
    right = A @ np.array([PATCH_W / 2 - 0.5 + PATCH_COLS_PER_W, PATCH_H / 2 - 0.5, 1.0])
    assert np.allclose(right, (132, 50))
    # the stem pointing up the photo gives the same columns (left stays left)
    assert np.allclose(patch_geometry((100.0, 50.0), (0.0, -1.0), 32.0)[:, 0], A[:, 0])
    with pytest.raises(ValueError):
        patch_geometry((0, 0), (0, 0), 10.0)


def test_edge_patch_puts_the_stem_in_the_middle_half():
    rgb = np.full((200, 300, 3), 30, np.uint8)
    rgb[:, 130:170] = 200                               # a bright vertical stem 40 px wide, x 130..169
    p, inside = edge_patch(rgb, (149.5, 100.0), (0, 1), 40.0)
    assert p.shape == (PATCH_H, PATCH_W, 3) and inside.all()
    row = p[PATCH_H // 2, :, 0].astype(float)
    bright = np.flatnonzero(row > 115)
    assert bright[0] == pytest.approx(PATCH_W / 4, abs=1.5) and bright[-1] == pytest.approx(3 * PATCH_W / 4 - 1, abs=1.5)
    # near the photo's border the patch is flagged outside there
    p2, inside2 = edge_patch(rgb, (20.0, 100.0), (0, 1), 40.0)
    assert inside2[:, -1].all() and not inside2[:, 0].any() and (p2[~inside2] == p2[~inside2][0]).all()


def test_decode_edge_logits():
    z = np.full((2, PATCH_W), -30.0)
    z[0, 30] = 4.0
    z[1, 90] = z[1, 91] = 4.0
    cols, mass = decode_edge_logits(z)
    assert cols.tolist() == pytest.approx([30.0, 90.5]) and (mass > 0.999).all()
    z[0, 100] = 4.0                                     # two far-apart peaks: half the mass each
    assert decode_edge_logits(z)[1][0] == pytest.approx(0.5, abs=1e-3)


def test_shipped_stem_edge_finder_finds_a_plain_stem():
    """On a plain bright stem on a dark background, given a rough width 20 % too wide and a centre
    a tenth of a width off, the shipped network's edges are within 1.5 px of the true ones."""
    from monodbh.models.runtime.common import load_manifest
    from monodbh.models.runtime.stem_edge import EdgeEstimate, StemEdgeFinder

    if "stem_edge" not in load_manifest().get("models", {}):
        pytest.skip("no stem-edge network shipped")
    finder = StemEdgeFinder(threads=1)
    assert finder.spec["kind"] == "stem_edge"
    rng = np.random.default_rng(0)
    rgb = (rng.normal(60, 8, (300, 400, 3))).clip(0, 255).astype(np.uint8)
    rgb[:, 180:220] = (rng.normal(150, 10, (300, 40, 3))).clip(0, 255).astype(np.uint8)   # x 180..219
    est = finder.find(rgb, (203.5, 150.0), (0.0, 1.0), 48.0)
    assert isinstance(est, EdgeEstimate) and est.across[0] > 0.99
    edges_x = 203.5 + est.offsets_px
    assert edges_x == pytest.approx([179.5, 219.5], abs=1.5)
    assert est.width_px == pytest.approx(40.0, abs=2.0) and (est.mass > 0.3).all()
