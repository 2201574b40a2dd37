"""monodbh.toolkit.evaluation.real_rope_bench: the painted rope is a band the rope detector finds where it was painted."""
import numpy as np

from monodbh.toolkit.evaluation.real_rope_bench import paint_rope, painted_hit, stem_row
from monodbh.toolkit.rope import detect_rope


def _trunk_scene(rng):
    """(H, W, 3) uint8 photo of a barky trunk (x 140..179) on foliage, and its instance map."""
    H, W = 240, 320
    img = np.empty((H, W, 3), np.float32)
    img[:] = (70, 110, 50)
    img += rng.normal(0, 12, img.shape)
    bark = 95 + 25 * np.sin(np.arange(40) / 3.0)[None, :, None] + rng.normal(0, 8, (H, 40, 1))
    img[:, 140:180] = np.concatenate([bark, 0.9 * bark, 0.75 * bark], axis=2)
    inst = np.zeros((H, W), np.uint16)
    inst[:, 140:180] = 1
    return np.clip(img, 0, 255).astype(np.uint8), inst


def test_stem_row_finds_the_trunk_and_not_a_blob():
    rng = np.random.default_rng(0)
    _, inst = _trunk_scene(rng)
    tid, y, xa, xb = stem_row(inst)
    assert tid == 1 and (xa, xb) == (140, 179) and 0 < y < 240
    blob = np.zeros((240, 320), np.uint16)
    blob[50:200, 20:300] = 2                      # wider than 60 % of the photo: no stem
    assert stem_row(blob) is None


def test_painted_rope_is_found_where_painted():
    rng = np.random.default_rng(1)
    img, inst = _trunk_scene(rng)
    out = paint_rope(img, 130, 140, 179, 3.0, 2.0, rng)
    changed = np.nonzero((out.astype(int) - img).any(2))
    assert changed[0].min() >= 125 and changed[0].max() <= 137            # only the band's rows
    assert changed[1].min() >= 137 and changed[1].max() <= 182          # (the 0.6 px blur)
    det = detect_rope(out, None)
    assert det, det.reason
    assert painted_hit(det.center_xy, 130, 140, 179, 3.0, 2.0)
    assert not painted_hit((160.0, 100.0), 130, 140, 179, 3.0, 2.0)
    assert not detect_rope(img, None)                                     # unpainted: no rope
