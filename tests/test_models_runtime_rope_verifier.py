"""The rope verifier's runtime: patch cutting and feeds, the shipped model."""
from types import SimpleNamespace

import numpy as np
import pytest

from monodbh.models.runtime.rope_verifier import (N_SIDE, PATCH_H, PATCH_W, band_patch, patch_feed, patch_geometry,
                                                  side_vector)


def _stem_photo(rope_rows=(60,), rope_rgb=(150, 60, 50)):
    """A grey-green vertical stem (x 80-120) on a light background with a thin red rope."""
    img = np.full((160, 200, 3), (200, 205, 210), np.uint8)
    img[:, 80:121] = (110, 125, 112)
    for r in rope_rows:
        img[r, 80:121] = rope_rgb
    mask = np.zeros(img.shape[:2], bool)
    mask[:, 80:121] = True
    return img, mask


def test_patch_geometry_centre_and_flipped_direction():
    A = patch_geometry((100.0, 60.0), (-1.0, 0.0), 40.0)        # pointing left: flipped to the right
    assert np.allclose(A @ [PATCH_W / 2 - 0.5, PATCH_H // 2, 1.0], [100.0, 60.0])
    assert A[0, 0] > 0 and np.isclose(A[0, 0], 40.0 * 2 / PATCH_W)
    with pytest.raises(ValueError):
        patch_geometry((0, 0), (0, 0), 10.0)


def test_band_patch_puts_the_rope_on_the_middle_row_with_the_stem_mask():
    img, mask = _stem_photo()
    p, st, ins = band_patch(img, mask, (100.0, 60.0), (1.0, 0.0), 40.0)
    assert p.shape == (PATCH_H, PATCH_W, 3) and st.shape == ins.shape == (PATCH_H, PATCH_W)
    mid = PATCH_H // 2
    red = p[..., 0].astype(int) - p[..., 1].astype(int)
    prof = red[:, PATCH_W // 2]
    assert int(np.argmax(prof)) == mid and prof.max() > 50
    # the stem fills the middle half of the columns
    cols = st[mid]
    assert cols[PATCH_W // 4 + 1: 3 * PATCH_W // 4 - 1].all() and not cols[:PATCH_W // 4 - 2].any()
    assert ins.all()
    # a wide stem: columns averaged, the one-pixel rope still stands out on its row
    big = np.full((400, 900, 3), (110, 125, 112), np.uint8)
    big[200, 100:800] = (150, 60, 50)
    p2, _, _ = band_patch(big, None, (450.0, 200.0), (1.0, 0.0), 300.0)
    r2 = p2[..., 0].astype(int) - p2[..., 1].astype(int)
    assert r2[:, 10:-10].mean(1).argmax() == mid
    # out of the photo: flagged outside
    _, _, ins3 = band_patch(img, mask, (5.0, 3.0), (1.0, 0.0), 40.0)
    assert not ins3.all() and ins3.any()


def test_patch_feed_and_side_vector():
    img, mask = _stem_photo()
    x = patch_feed(*band_patch(img, mask, (100.0, 60.0), (1.0, 0.0), 40.0))
    assert x.shape == (5, PATCH_H, PATCH_W) and x.dtype == np.float32
    v = side_vector({"log_zpix": 2.0, "main": 1.0})
    assert v.shape == (N_SIDE,) and v.sum() == 3.0


def test_shipped_rope_verifier_prefers_the_rope_row():
    from monodbh.models.runtime import load_manifest
    from monodbh.models.runtime.rope_verifier import RopeVerifier

    if "rope_verifier" not in load_manifest().get("models", {}):
        pytest.skip("no shipped rope verifier")
    ver = RopeVerifier(threads=1)
    img, mask = _stem_photo(rope_rgb=(135, 95, 85))           # faint rope
    feats = {"log_contrast": np.log(0.03), "log_zpix": np.log(6.0), "log_zprof": np.log(8.0),
             "log_width": np.log(41.0), "red_shift": 0.8}
    bands = [SimpleNamespace(center_xy=(100.0, y), direction=(1.0, 0.0), width_px=41, features=feats)
             for y in (60.0, 110.0)]
    z = ver.logits(img, [mask, mask], bands)
    assert z.shape == (2,) and z[0] > z[1]
