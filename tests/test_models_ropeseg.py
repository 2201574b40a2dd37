"""Rope finder: bank cutting, the network, tiling, candidates, training, export hooks, the shipped model."""
import json

import numpy as np
import pytest
import torch

from monodbh.models.modeling import build
from monodbh.models.runtime_ropeseg import BORDER, TILE, rope_components, tile_origins
from monodbh.models.training.ropeseg_bank import TILE as BANK_TILE, cut_photo


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


def test_cut_photo_targets_align_with_the_rope():
    img, rope, inst = _roped_photo()
    crops = cut_photo(img, rope, inst, np.random.default_rng(0), n_pos=3, n_rand=2)
    kinds = [k for _, _, k in crops]
    assert kinds.count(0) == 3 and 1 in kinds and 2 in kinds and kinds.count(3) == 2
    for rgb, t, k in crops:
        assert rgb.shape == (BANK_TILE, BANK_TILE, 3) and t.shape == (BANK_TILE // 2, BANK_TILE // 2)
        if k == 0:
            assert t.any()
            # target cells hold red pixels
            ys, xs = np.nonzero(t)
            blk = rgb[2 * ys[0]:2 * ys[0] + 2, 2 * xs[0]:2 * xs[0] + 2].astype(int)
            assert (blk[..., 0] - blk[..., 1]).max() > 80
    _, rope0, _ = _roped_photo(rope_rgb=None)
    crops0 = cut_photo(img, rope0, inst, np.random.default_rng(0))
    assert not any(k == 0 for _, _, k in crops0) and not any(t.any() for _, t, _ in crops0)


def test_ropeseg_onnx_matches_torch(tmp_path):
    from monodbh.models.export.onnx_io import export_onnx

    torch.manual_seed(0)
    g = build("ropeseg", "tiny").eval()
    assert g(torch.randn(2, 3, 64, 64)).shape == (2, 1, 32, 32)
    res = export_onnx(g, g.spec, tmp_path / "ropeseg.onnx", check=True, atol=1e-4)
    assert max(res["max_abs_err"].values()) < 1e-4


def _bank(path, n_photos=3, seed=0):
    from monodbh.models.training.ropeseg_bank import cut_photo
    rgbs, tgts = [], []
    for i in range(n_photos):
        img, rope, inst = _roped_photo(row=200 + 20 * i, rope_rgb=(170, 40, 35) if i < 2 else None)
        for rgb, t, k in cut_photo(img, rope, inst, np.random.default_rng([seed, i])):
            rgbs.append(rgb)
            tgts.append(t)
    np.savez(path, rgb=np.stack(rgbs), target=np.stack(tgts), photo=np.zeros(len(rgbs), np.int64),
             kind=np.zeros(len(rgbs), np.int64))


def test_train_ropeseg_smoke_resume_metrics_and_hooks(tmp_path):
    from monodbh.models.modeling import get_spec
    from monodbh.models.training.common import calibration_inputs, evaluate_kind, make_source
    from monodbh.models.training.ropeseg import tile_metrics, train_ropeseg

    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    _bank(a, seed=0)
    _bank(b, seed=1)
    opts = dict(size="tiny", batch_size=4, crop=64, threads=1, warmup_steps=1, log_every=1, val_every=1)
    r = train_ropeseg(str(tmp_path / "run"), 2, [str(a)], val_data=[str(b)], stop_at=1, verbose=False, **opts)
    assert r["step"] == 1
    r = train_ropeseg(str(tmp_path / "run"), 2, resume=True, verbose=False)
    assert r["step"] == 2 and {"tile_auc", "recall", "precision"} <= set(r["val"])
    cfg = json.loads((tmp_path / "run" / "config.json").read_text())
    assert cfg["kind"] == "ropeseg" and cfg["data"]["type"] == "banks" and cfg["train"]["crop"] == 64
    src = make_source([str(b)])
    spec = get_spec("ropeseg", "tiny")
    feeds = calibration_inputs("ropeseg", 4, 0, spec, src)      # 2 x 2 bank tiles per graph tile
    assert len(feeds) == 4 and feeds[0]["image"].shape == (1, 3, TILE, TILE)
    g = build("ropeseg", "tiny").eval()

    def predict(f):
        with torch.no_grad():
            return {"logit": g(torch.from_numpy(f["image"])).numpy()}

    m = evaluate_kind("ropeseg", predict, 6, 0, spec, src)
    assert 0.0 <= m["tile_auc"] <= 1.0
    # metrics: the target itself as logits is perfect, its negative is not
    t = src.arrays["target"]
    z = np.where(t > 0, 5.0, -5.0).astype(np.float32)
    mm = tile_metrics(z, t)
    assert mm["tile_auc"] == 1.0 and mm["recall"] == 1.0 and mm["precision"] == 1.0
    assert tile_metrics(-z, t)["recall"] == 0.0
    with pytest.raises(ValueError, match="crop"):
        train_ropeseg(str(tmp_path / "run2"), 1, [str(a)], **{**opts, "crop": 63})


def _shipped_finder():
    from monodbh.models.runtime import load_manifest
    from monodbh.models.runtime_ropeseg import RopeFinder

    if "ropeseg" not in load_manifest().get("models", {}):
        pytest.skip("no shipped rope finder")
    return RopeFinder(threads=1)


def test_shipped_rope_finder_finds_a_rope_and_nothing_without_one():
    from monodbh.toolkit.rope_finder import rope_from_finder

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
    from monodbh.models.runtime_ropeseg import knot_band

    ys, xs = np.arange(40), np.full(40, 7)
    assert knot_band(ys, xs) is None
    ys = np.r_[np.full(30, 10), np.arange(11, 25)]
    xs = np.r_[np.arange(30), np.full(14, 20)]
    assert knot_band(ys, xs)[:30].all()
