"""training.trunk_net: the trunk network's decoder on frozen backbone features, its tiled map."""
import numpy as np
import pytest
import torch

from monodbh.models.modeling.efficientnet_lite import FEATURE_CHANNELS
from monodbh.models.modeling.trunk_net import TrunkNet, TrunkNetConfig, TrunkNetHead
from monodbh.models.training import trunk_net as tn


def test_modules_check_their_inputs():
    with pytest.raises(ValueError, match="images"):
        TrunkNet()(torch.zeros(1, 4, 64, 64))
    with pytest.raises(ValueError, match="feature maps"):
        TrunkNetHead()([torch.zeros(1, 24, 8, 8)])


def _features(n=12, seed=0):
    # four feature maps whose first channel says "trunk" in a band of columns of the first map
    rng = np.random.default_rng(seed)
    F = [rng.standard_normal((n, c, 16 >> i, 16 >> i)).astype(np.float16) for i, c in enumerate(FEATURE_CHANNELS)]
    Y = np.zeros((n, tn.LABEL_SIDE, tn.LABEL_SIDE), np.uint8)
    for k in range(n):
        c = int(rng.integers(3, 12))
        F[0][k, 0] = -2
        F[0][k, 0, :, c:c + 3] = 2
        Y[k, :, c * 16:(c + 3) * 16] = 255
    return F, Y


def test_a_few_steps_learn_a_trunk_and_a_resumed_run_ends_the_same(tmp_path, monkeypatch):
    F, Y = _features()
    monkeypatch.setattr(tn, "load_features", lambda folder, backbone, cache, *a, **k: (F, Y))
    kw = dict(steps=60, batch=4, lr=1e-2, checkpoint_every=20, cfg=TrunkNetConfig(lat=4, ch=8),
              pretrained=False, log=lambda *_: None, threads=1, views=0)
    scores = tn.train(tmp_path / "a", ["x"], ["x"], **kw)
    assert scores["x"]["iou"] > 0.8 and scores["x"]["photos"] == 12
    assert tn.train(tmp_path / "b", ["x"], ["x"], stop_at=40, **kw) == {}
    assert not (tmp_path / "b" / "head.pt").exists()
    tn.train(tmp_path / "b", ["x"], ["x"], resume=True, **kw)
    a, b = torch.load(tmp_path / "a" / "head.pt"), torch.load(tmp_path / "b" / "head.pt")
    assert all(torch.equal(a[k], b[k]) for k in a)
    net = tn.load_net(tmp_path / "b")
    assert net.head.cfg.ch == 8 and not net.training


def test_the_tiled_map_covers_the_photo_and_matches_one_pass_in_a_single_tile():
    torch.manual_seed(0)
    net = TrunkNet(TrunkNetConfig(lat=4, ch=8)).eval()
    rgb = np.random.default_rng(1).integers(0, 255, (90, 120, 3), dtype=np.uint8)
    one = tn.trunk_map(net, rgb, tile_frac=None)
    assert one.shape == (90, 120) and one.dtype == np.float32 and 0 <= one.min() and one.max() <= 1
    tiled = tn.trunk_map(net, rgb, tile_frac=0.5)                     # 6 tiles of 60 px
    assert tiled.shape == (90, 120) and np.isfinite(tiled).all() and not np.allclose(tiled, one)
    assert np.allclose(tn.trunk_map(net, rgb, tile_frac=1.0), one, atol=1e-6)
    assert tn.trunk_map(net, rgb, size=(60, 45), tile_frac=None).shape == (45, 60)
    with pytest.raises(ValueError, match="photo"):
        tn.photo_input(np.zeros((8, 8), np.uint8))


def test_eval_refuses_a_tile_fraction_out_of_range(tmp_path):
    with pytest.raises(SystemExit):
        tn.main(["eval", str(tmp_path), "--tiles", "1.5"])


def test_ship_lists_the_network_and_the_runtime_reads_its_map(tmp_path):
    pytest.importorskip("embreex")
    import hashlib
    import json
    import shutil

    from monodbh.models.runtime.common import MODELS_DIR
    from monodbh.models.runtime.trunk_net import TrunkNet as RuntimeTrunkNet
    from monodbh.models.synthetic import generate_sample
    from monodbh.models.synthetic.io import read_sample, write_sample
    data = tmp_path / "data"
    for i in range(2):
        write_sample(data, i, generate_sample(11, i, (128, 96)))
    run = tmp_path / "run"
    run.mkdir()
    torch.manual_seed(0)
    torch.save(TrunkNetHead(TrunkNetConfig(lat=4, ch=8)).state_dict(), run / "head.pt")
    (run / "config.json").write_text(json.dumps({"data": ["x"], "steps": 1, "photos": 2, "views": 0, "pretrained": False,
                                                 "head": {"lat": 4, "ch": 8, "dilations": [1, 2, 4, 8]}}))
    mdir = tmp_path / "models"
    mdir.mkdir()
    shutil.copy(MODELS_DIR / "manifest.json", mdir)
    out = tn.ship(run, data, [data], models_dir=mdir, n_calib=2)
    entry = json.loads((mdir / "manifest.json").read_text())["models"]["trunk_net"]
    path = mdir / entry["file"]
    assert entry["file"] == "trunk_net_int8.onnx" and entry["spec"]["kind"] == "trunk_net"
    assert entry["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest() and entry["precision"] == "int8"
    assert set(out["validation"]) == {"data"} and out["validation"]["data"]["photos"] == 2
    net = RuntimeTrunkNet(path)
    rgb = read_sample(data, 0)["rgb"]
    assert net.logits(rgb).shape == (64, 64) and net.threshold == 0.5
    full = net.trunk_map(rgb)
    assert full.shape == rgb.shape[:2] and 0 <= full.min() and full.max() <= 1
    assert net.trunk_map(rgb, size=(64, 48), tile_frac=None).shape == (48, 64)
