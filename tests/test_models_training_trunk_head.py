"""training.trunk_head: the head on a segmenter's features, attached without touching its outputs."""
import json

import numpy as np
import pytest
import torch

from monodbh.models.modeling.trunk_head import TrunkHead, TrunkHeadConfig
from monodbh.models.runtime.segmenter import FEATURES_OUTPUT, Segmenter, trunk_probability
from monodbh.models.training import trunk_head as th


@pytest.fixture(scope="module")
def tiny_segmenter(tmp_path_factory):
    from monodbh.models.export import export_onnx
    from monodbh.models.modeling import build

    m = build("segmenter", "tiny")
    p = tmp_path_factory.mktemp("trunk") / "segmenter.onnx"
    export_onnx(m, m.spec, p)
    return p


def test_head_shapes_and_input_check():
    head = TrunkHead(TrunkHeadConfig(in_ch=32, ch=8))
    assert head(torch.zeros(3, 32, 16, 20)).shape == (3, 1, 16, 20)
    with pytest.raises(ValueError, match=r"\(B, 32, h, w\)"):
        head(torch.zeros(1, 16, 16, 16))


def test_exposed_features_leave_the_other_outputs_bit_identical_and_feed_the_int8_head(tiny_segmenter, tmp_path):
    torch.manual_seed(0)
    head = TrunkHead(TrunkHeadConfig(in_ch=32, ch=8)).eval()
    for m in head.modules():                       # non-trivial BatchNorm statistics
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
    seg_path = tmp_path / "segmenter.onnx"
    th.expose_features(tiny_segmenter, seg_path)
    with pytest.raises(ValueError, match="already has a mask_features output"):
        th.expose_features(seg_path, tmp_path / "twice.onnx")
    rng = np.random.default_rng(1)
    photos = [rng.integers(0, 255, (48, 80, 3), dtype=np.uint8) for _ in range(3)]
    assert th._same_outputs(tiny_segmenter, seg_path, photos)
    ext = th.FeatureExtractor(tiny_segmenter)
    feats = np.stack([ext(p) for p in photos])
    assert feats.shape == (3, 32, 16, 16)
    head_path = th.export_head(head, tmp_path / "trunk_head_int8.onnx", feats, {"note": "test"}, side=16)
    old = Segmenter(tiny_segmenter)
    new = Segmenter(seg_path, trunk_head=head_path)
    assert not old.has_trunk and new.has_trunk and new.trunk_threshold == th.THRESHOLD
    assert not Segmenter(seg_path).has_trunk          # a file of one's own: no shipped head assumed
    cls, msk, tl = new.raw_with_trunk(photos[0])
    a = old.raw(photos[0])
    assert np.array_equal(cls, a[0]) and np.array_equal(msk, a[1]) and tl.shape == (16, 16)
    with torch.no_grad():
        ref = head(torch.from_numpy(feats[:1]))[0, 0].numpy()
    # the int8 head follows the float one to within its quantisation
    assert np.corrcoef(tl.ravel(), ref.ravel())[0, 1] > 0.98
    res = new.predict(photos[0], size=(40, 24), trunk=True)
    assert res.trunk_prob.shape == (24, 40) and 0 <= res.trunk_prob.min() <= res.trunk_prob.max() <= 1
    assert old.predict(photos[0]).trunk_prob is None
    with pytest.raises(Exception, match="no trunk head"):
        old.predict(photos[0], trunk=True)
    with pytest.raises(ValueError, match="expected mask features"):
        new._trunk_head().logits(np.zeros((1, 32, 8, 8), np.float32))
    # the trunk map: one pass equals predict's; in tiles, the mean of the tiles' maps
    whole = new.trunk_map(photos[0], tile_frac=None)
    np.testing.assert_array_equal(whole, new.predict(photos[0], trunk=True).trunk_prob)
    tiled = new.trunk_map(photos[0], size=(40, 24))
    assert tiled.shape == (24, 40) and 0 <= tiled.min() <= tiled.max() <= 1
    # 40 px tiles of the 80 x 48 photo start at x 0, 20, 40 and y 0, 8: the corner x < 20, y < 8
    # lies in the first tile only
    first = trunk_probability(new.raw_with_trunk(np.ascontiguousarray(photos[0][:40, :40]))[2], (40, 40))
    full = new.trunk_map(photos[0], tile_frac=0.5)
    np.testing.assert_allclose(full[:8, :20], first[:8, :20], atol=1e-6)
    assert not np.allclose(full[20:30, 20:30], first[20:30, 20:30], atol=1e-6)
    with pytest.raises(ValueError, match="tile fraction"):
        new.trunk_map(photos[0], tile_frac=1.5)


def test_trunk_probability_upsamples_in_logit_space():
    lo = np.array([[-4.0, 4.0]], np.float32)
    p = trunk_probability(lo, (4, 1))
    assert p.shape == (1, 4) and p[0, 0] < 0.05 and p[0, -1] > 0.95
    assert np.all(np.diff(p[0]) >= 0)
    with pytest.raises(ValueError, match=r"\(h, w\)"):
        trunk_probability(np.zeros((1, 2, 2), np.float32), (4, 4))


def test_tile_views_are_square_crops_whose_label_stays_on_their_pixels():
    # a photo whose red channel is the stem label: every crop's label must be its own red pixels
    H, W = 90, 120
    stem = np.zeros((H, W), bool)
    stem[:, 50:62] = True
    stem[20:30, :] = True
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[..., 0] = stem * 200
    views = th.tile_views(rgb, stem, 40, np.random.default_rng(3))
    sides = [v[0].shape[0] for v in views]
    assert all(v[0].shape == (s, s, 3) and v[1].shape == (s, s) for v, s in zip(views, sides))
    assert 0.4 * W - 1 <= min(sides) and max(sides) <= H        # (0.4-0.75) x long side, at most the short
    jittered = 0
    for crop, lab in views:
        same = np.array_equal(crop[..., 0] > 100, lab)
        jittered += not np.array_equal(crop[..., 0], lab * np.uint8(200))
        assert same or np.mean((crop[..., 0] > crop[..., 0].mean()) == lab) > 0.9
    assert 5 < jittered < 35                                    # about half jittered
    again = th.tile_views(rgb, stem, 40, np.random.default_rng(3))
    assert all(np.array_equal(a[0], b[0]) for a, b in zip(views, again))


def test_turned_tile_views_keep_the_label_on_their_pixels_and_leave_upright_runs_unchanged():
    # a vertical stem whose red channel is its label: a turned crop's label must follow its pixels
    H, W = 90, 120
    stem = np.zeros((H, W), bool)
    stem[:, 50:62] = True
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[..., 0] = stem * 200
    views = th.tile_views(rgb, stem, 40, np.random.default_rng(5), tilt_deg=60)
    turned = 0
    for crop, lab in views:
        assert crop.shape[:2] == lab.shape and lab.dtype == bool
        red = crop[..., 0] > 100
        assert np.mean(red == lab) > 0.97 or np.mean((crop[..., 0] > crop[..., 0].mean()) == lab) > 0.9
        cols = np.nonzero(lab.any(0))[0]
        # an upright stem keeps 12 columns; a turned one spreads over many more
        turned += len(cols) > 16 and lab.sum() > 0
    assert 8 < turned < 32                                       # about half of the crops turned
    upright = th.tile_views(rgb, stem, 40, np.random.default_rng(3))
    again = th.tile_views(rgb, stem, 40, np.random.default_rng(3), tilt_deg=0)
    assert all(np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) for a, b in zip(upright, again))


def test_jittered_photo_keeps_shape_and_order_of_brightness():
    rng = np.random.default_rng(0)
    ramp = np.tile(np.linspace(0, 255, 64).astype(np.uint8)[None, :, None], (8, 1, 3))
    for _ in range(10):
        out = th.jitter_photo(ramp, rng)
        assert out.shape == ramp.shape and out.dtype == np.uint8
        assert out[4, -4].mean() > out[4, 3].mean() + 40


def test_a_few_steps_learn_a_trunk_from_features_and_a_resumed_run_ends_the_same(tmp_path, monkeypatch):
    # features that say "trunk" in channel 0: the head must learn them within a few steps, and a
    # run stopped half-way and resumed must end with the weights of an uninterrupted one
    rng = np.random.default_rng(0)
    F = rng.standard_normal((12, 32, 16, 16)).astype(np.float16)
    Y = np.zeros((12, th.LABEL_SIDE, th.LABEL_SIDE), np.uint8)
    for i in range(12):
        c = int(rng.integers(3, 12))
        F[i, 0] = -2
        F[i, 0, :, c:c + 3] = 2
        Y[i, :, c * 16:(c + 3) * 16] = 255

    class Ext:
        sha256 = "0" * 64

        def __init__(self, *a, **k):
            pass
    monkeypatch.setattr(th, "FeatureExtractor", Ext)
    monkeypatch.setattr(th, "load_features", lambda folder, ext, cache, *views: (F, Y))
    kw = dict(steps=60, batch=4, lr=1e-2, checkpoint_every=20, head_cfg=TrunkHeadConfig(in_ch=32, ch=8),
              log=lambda *_: None, threads=1)
    scores = th.train(tmp_path / "a", ["x"], ["x"], **kw)
    assert scores["x"]["iou"] > 0.8 and scores["x"]["photos"] == 12
    assert th.train(tmp_path / "b", ["x"], ["x"], stop_at=40, **kw) == {}
    assert not (tmp_path / "b" / "head.pt").exists()
    th.train(tmp_path / "b", ["x"], ["x"], resume=True, **kw)
    a = torch.load(tmp_path / "a" / "head.pt")
    b = torch.load(tmp_path / "b" / "head.pt")
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert th._load_head(tmp_path / "b").cfg.ch == 8


def test_ship_attaches_the_head_and_restamps_the_error_model_only_for_its_segmenter(tiny_segmenter, tmp_path):
    import hashlib
    import shutil

    pytest.importorskip("embreex")
    from monodbh.models.synthetic import generate_sample
    from monodbh.models.synthetic.io import write_sample
    models = tmp_path / "models"
    models.mkdir()
    shutil.copy(tiny_segmenter, models / "segmenter_int8.onnx")
    old = hashlib.sha256((models / "segmenter_int8.onnx").read_bytes()).hexdigest()
    manifest = {"format": 1, "models": {"segmenter": {"file": "segmenter_int8.onnx", "sha256": old}},
                "error_model": {"models": {"segmenter": old, "depth": "d" * 64}, "sigma": {"network": 0.2}}}
    (models / "manifest.json").write_text(json.dumps(manifest))
    val = tmp_path / "val"
    write_sample(val, 0, generate_sample(5, 2, (160, 120)))
    run = tmp_path / "run"
    run.mkdir()
    cfg = TrunkHeadConfig(in_ch=32, ch=8)
    torch.save(TrunkHead(cfg).state_dict(), run / "head.pt")
    conf = {"data": [str(val)], "steps": 1, "photos": 1, "segmenter_sha256": "f" * 64,
            "head": {"in_ch": 32, "ch": 8, "dilations": [1, 2, 4, 8]}}
    (run / "config.json").write_text(json.dumps(conf))
    with pytest.raises(ValueError, match="another segmenter's features"):
        th.ship(run, [val], models)
    (run / "config.json").write_text(json.dumps({**conf, "segmenter_sha256": old}))
    out = th.ship(run, [val], models, n_calib=1)
    man = json.loads((models / "manifest.json").read_text())
    new = hashlib.sha256((models / "segmenter_int8.onnx").read_bytes()).hexdigest()
    assert out["error_model_restamped"]
    assert man["models"]["segmenter"]["sha256"] == new == man["error_model"]["models"]["segmenter"] != old
    assert man["models"]["segmenter"]["features_of"] == old
    assert man["error_model"]["models"]["depth"] == "d" * 64
    assert FEATURES_OUTPUT in [o["name"] for o in man["models"]["segmenter"]["outputs"]]
    head = man["models"]["trunk_head"]
    assert head["file"] == "trunk_head_int8.onnx" and head["spec"]["kind"] == "trunk_head"
    assert head["sha256"] == hashlib.sha256((models / "trunk_head_int8.onnx").read_bytes()).hexdigest()
    assert set(head["validation"]["int8"]) == {"val"}
    seg = Segmenter(manifest=man, trunk_head=models / head["file"], path=models / "segmenter_int8.onnx")
    assert seg.has_trunk
    assert sorted(p.name for p in models.iterdir()) == ["manifest.json", "segmenter_int8.onnx", "trunk_head_int8.onnx"]
    # a second head on the same features ships without touching the segmenter again
    again = th.ship(run, [val], models, n_calib=1)
    assert not again["error_model_restamped"]
    assert hashlib.sha256((models / "segmenter_int8.onnx").read_bytes()).hexdigest() == new


def test_the_shipped_head_is_scored_on_folders_with_the_stem_label_only(tmp_path, drop_npz_member):
    pytest.importorskip("embreex")
    from monodbh.models.synthetic import generate_sample
    from monodbh.models.synthetic.io import write_sample
    s = generate_sample(11, 0, (384, 288))
    write_sample(tmp_path / "new", 0, s)
    r = th.score_shipped(tmp_path / "new")
    assert r["photos"] == 1 and 0.3 < r["iou"] <= 1 and r["threshold"] == th.THRESHOLD
    t = th.score_shipped(tmp_path / "new", tiles=0.5)              # dbh reconstruct's map, full size
    assert t["tiles"] == 0.5 and 0.3 < t["iou"] <= 1 and t["iou"] != r["iou"]
    lo = th.score_shipped(tmp_path / "new", threshold=0.2)       # more pixels called trunk
    assert lo["threshold"] == 0.2 and lo["recall"] >= r["recall"] and lo["precision"] <= r["precision"]
    with pytest.raises(ValueError, match="scores the shipped head only"):
        th._eval_cmd([tmp_path / "new"], tmp_path, tiles=0.5)
    old = tmp_path / "old"
    write_sample(old, 0, s)
    p = old / "000000.npz"
    drop_npz_member(p, "stem.npy")
    assert th.score_shipped(old) == {}
    with pytest.raises(ValueError, match="no samples with a 'stem' label"):
        th._eval_cmd([old], None)
