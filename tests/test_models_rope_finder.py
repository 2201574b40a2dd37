"""Rope finder: bank cutting, the network, training, export hooks (the runtime: test_models_runtime_rope_finder)."""
import json

import numpy as np
import pytest
import torch

from monodbh.models.modeling import build
from monodbh.models.runtime.rope_finder import TILE
from monodbh.models.training.rope_finder_bank import TILE as BANK_TILE, cut_photo
from test_models_runtime_rope_finder import _roped_photo


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


def test_rope_finder_onnx_matches_torch(tmp_path):
    from monodbh.models.export.onnx_io import export_onnx

    torch.manual_seed(0)
    g = build("rope_finder", "tiny").eval()
    assert g(torch.randn(2, 3, 64, 64)).shape == (2, 1, 32, 32)
    res = export_onnx(g, g.spec, tmp_path / "rope_finder.onnx", check=True, atol=1e-4)
    assert max(res["max_abs_err"].values()) < 1e-4


def _bank(path, n_photos=3, seed=0):
    from monodbh.models.training.rope_finder_bank import cut_photo
    rgbs, tgts = [], []
    for i in range(n_photos):
        img, rope, inst = _roped_photo(row=200 + 20 * i, rope_rgb=(170, 40, 35) if i < 2 else None)
        for rgb, t, k in cut_photo(img, rope, inst, np.random.default_rng([seed, i])):
            rgbs.append(rgb)
            tgts.append(t)
    np.savez(path, rgb=np.stack(rgbs), target=np.stack(tgts), photo=np.zeros(len(rgbs), np.int64),
             kind=np.zeros(len(rgbs), np.int64))


def test_train_rope_finder_smoke_resume_metrics_and_hooks(tmp_path):
    from monodbh.models.modeling import get_spec
    from monodbh.models.training.common import calibration_inputs, evaluate_kind, make_source
    from monodbh.models.training.rope_finder import tile_metrics, train_rope_finder

    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    _bank(a, seed=0)
    _bank(b, seed=1)
    opts = dict(size="tiny", batch_size=4, crop=64, threads=1, warmup_steps=1, log_every=1, val_every=1)
    r = train_rope_finder(str(tmp_path / "run"), 2, [str(a)], val_data=[str(b)], stop_at=1, verbose=False, **opts)
    assert r["step"] == 1
    r = train_rope_finder(str(tmp_path / "run"), 2, resume=True, verbose=False)
    assert r["step"] == 2 and {"tile_auc", "recall", "precision"} <= set(r["val"])
    cfg = json.loads((tmp_path / "run" / "config.json").read_text())
    assert cfg["kind"] == "rope_finder" and cfg["data"]["type"] == "banks" and cfg["train"]["crop"] == 64
    src = make_source([str(b)])
    spec = get_spec("rope_finder", "tiny")
    feeds = calibration_inputs("rope_finder", 4, 0, spec, src)      # 2 x 2 bank tiles per graph tile
    assert len(feeds) == 4 and feeds[0]["image"].shape == (1, 3, TILE, TILE)
    g = build("rope_finder", "tiny").eval()

    def predict(f):
        with torch.no_grad():
            return {"logit": g(torch.from_numpy(f["image"])).numpy()}

    m = evaluate_kind("rope_finder", predict, 6, 0, spec, src)
    assert 0.0 <= m["tile_auc"] <= 1.0
    # metrics: the target itself as logits is perfect, its negative is not
    t = src.arrays["target"]
    z = np.where(t > 0, 5.0, -5.0).astype(np.float32)
    mm = tile_metrics(z, t)
    assert mm["tile_auc"] == 1.0 and mm["recall"] == 1.0 and mm["precision"] == 1.0
    assert tile_metrics(-z, t)["recall"] == 0.0
    with pytest.raises(ValueError, match="crop"):
        train_rope_finder(str(tmp_path / "run2"), 1, [str(a)], **{**opts, "crop": 63})
