"""Tree silhouette network: U-Net export, crop geometry/targets, Cycle-GAN training smoke runs."""
import json

import numpy as np
import pytest
import torch

from monodbh.models.modeling import build
from monodbh.models.modeling.tree import build_tree_cycle


def fake_tree_sample(seed=0, W=64, H=48, dbh=0.5, dist=3.0):
    """A vertical round stem of diameter ``dbh`` at ``dist`` m straight ahead of a level camera."""
    rng = np.random.default_rng(seed)
    f = 0.8 * W
    R = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]             # cam x = world x, cam y = -world z
    u = np.arange(W)[None, :].repeat(H, 0)
    x = (u - (W / 2 - 0.5)) * dist / f
    r = dbh / 2
    inst = (np.abs(x) <= r).astype(np.uint16)
    off = np.sqrt(np.clip(r * r - x * x, 0, None))
    z1 = np.where(inst > 0, dist - off, 0).astype(np.float32)
    z2 = np.where(inst > 0, dist + off, 0).astype(np.float32)
    depth = np.where(inst > 0, z1, 8.0).astype(np.float32)
    depth[:5] = 0
    tree = {"id": 1, "dbh_m": dbh, "r_bh_m": r, "position_world": [0, dist, 0],
            "axis_world": [0, 0, 1], "taper": 0.0, "flare": 0.0}
    meta = {"K": [[f, 0, W / 2 - 0.5], [0, f, H / 2 - 0.5], [0, 0, 1]], "dist": [0.0] * 5,
            "width": W, "height": H, "R_world_from_cam": R, "t_world_from_cam": [0, 0, 1.5],
            "trees": [tree], "roped_tree": 1,
            "rope": {"tree": 1, "height_m": 1.3, "center_world": [0, dist, 1.3]}}
    return {"rgb": rng.integers(0, 255, (H, W, 3), dtype=np.uint8), "depth": depth,
            "instance": inst, "semantic": (inst > 0).astype(np.uint8) * 3,
            "rope": np.zeros((H, W), bool), "z1": z1, "z2": z2, "meta": meta}


def test_unet_shapes_and_cycle_parts():
    torch.manual_seed(0)
    g = build("tree", "tiny")
    p = g.spec.inputs[0].shape[-1]
    x = torch.randn(2, 4, p, p)
    y = g(x)
    assert y.shape == (2, 2, p, p) and float(y.abs().max()) <= 1.0
    parts = build_tree_cycle("tiny")
    assert parts["F"](x).shape == (2, 3, p, p)
    assert parts["D_Y"](torch.randn(2, 3, p, p)).shape == (2, 1)
    assert not any(isinstance(m, torch.nn.ConvTranspose2d) for m in g.modules())


def test_unet_onnx_matches_torch(tmp_path):
    from monodbh.models.export.onnx_io import export_onnx

    torch.manual_seed(0)
    g = build("tree", "tiny").eval()
    res = export_onnx(g, g.spec, tmp_path / "tree.onnx", check=True, atol=1e-4)
    assert max(res["max_abs_err"].values()) < 1e-4


def test_crop_targets_of_round_stem():
    from monodbh.models.training.tree import (TreeTrainConfig, choose_crop, stem_point_cam,
                                               tree_example, tree_metrics)

    s = fake_tree_sample()
    pc = stem_point_cam(s["meta"], s["meta"]["trees"][0], 1.3)
    np.testing.assert_allclose(pc, [0.0, 0.2, 3.0], atol=1e-9)
    cfg = TreeTrainConfig(center_jitter=0.0, p_rope=1.0)
    c = choose_crop(s, np.random.default_rng(0), cfg, k=4.0)
    assert c["roped"] and abs(c["z_ref"] - 3.0) < 1e-9
    assert abs(c["width_px"] - 0.5 * 51.2 / 3.0) < 1e-6 and abs(c["side_px"] - 4 * c["width_px"]) < 1e-6
    ex = tree_example(s, c, 64)
    P = 64
    R, G = ex["target"][:, P // 2 - 1:P // 2 + 1, P // 2 - 1:P // 2 + 1]
    # through the axis of a round stem: R_n = -r f / (z S) = -1 / (2k), G_n = 2r f / (z S) = 1 / k
    np.testing.assert_allclose(R, -1 / 8, atol=0.01)
    np.testing.assert_allclose(G, 1 / 4, atol=0.02)
    m = tree_metrics(ex["target"], ex)
    assert m["g_within10"] == 1.0 and m["g_acc"] == 1.0 and m["front_absrel"] == 0.0
    assert not ex["valid"][0, :, :8].any()                       # background ignored


def test_train_tree_smoke_and_resume(tmp_path):
    from monodbh.models.training.tree import train_tree

    data = [fake_tree_sample(i) for i in range(3)]
    opts = dict(size="tiny", batch_size=4, crops_per_sample=2, val_n=2, threads=1,
                warmup_steps=1, log_every=1, mode="cycle+sup", verbose=False)
    a, b = tmp_path / "a", tmp_path / "b"
    r = train_tree(a, 3, data, stop_at=2, **opts)
    assert r["step"] == 2
    cfg = json.loads((a / "config.json").read_text())
    assert cfg["kind"] == "tree" and cfg["train"]["mode"] == "cycle+sup"
    ck = torch.load(a / "checkpoint.pt", weights_only=False)
    assert set(ck["extra"]) == {"F", "D_X", "D_Y", "opt_d"}
    r = train_tree(a, 3, data, resume=True, verbose=False)
    assert r["step"] == 3 and "g_acc" in r["val"] and "front_absrel" in r["val"]
    logs = [json.loads(l) for l in (a / "log.jsonl").read_text().splitlines()]
    assert [l["step"] for l in logs if l["kind"] == "train"] == [1, 2, 3]
    assert all(k in logs[0] for k in ("sup", "g_gan", "cyc", "idt", "d_loss"))
    train_tree(b, 3, data, **opts)
    wa = torch.load(a / "checkpoint.pt", weights_only=False)["model"]
    wb = torch.load(b / "checkpoint.pt", weights_only=False)["model"]
    assert all(torch.allclose(wa[k].float(), wb[k].float(), atol=1e-5) for k in wa)


@pytest.mark.parametrize("mode", ["sup", "cycle"])  # cycle+sup: smoke/resume test above
def test_train_tree_modes(tmp_path, mode):
    from monodbh.models.training.tree import train_tree

    r = train_tree(tmp_path / mode, 1, [fake_tree_sample(0)], size="tiny", batch_size=2,
                    crops_per_sample=2, val_n=1, threads=1, mode=mode, verbose=False)
    assert r["step"] == 1
    extra = torch.load(tmp_path / mode / "checkpoint.pt", weights_only=False)["extra"]
    assert ("F" in extra) == (mode == "cycle")


def test_tree_export_hooks():
    from monodbh.models.modeling import get_spec
    from monodbh.models.training.common import ListSource, calibration_inputs, evaluate_kind

    spec = get_spec("tree", "tiny")
    src = ListSource([fake_tree_sample(i) for i in range(2)])
    feeds = calibration_inputs("tree", 3, 0, spec, src)
    assert len(feeds) == 3 and feeds[0]["crop"].shape == (1, 4, 64, 64)
    g = build("tree", "tiny").eval()

    def predict(f):
        with torch.no_grad():
            return {"silhouette": g(torch.from_numpy(f["crop"])).numpy()}

    m = evaluate_kind("tree", predict, 2, 0, spec, src)
    assert spec.metric == "g_acc" and 0.0 <= m["g_acc"] <= 1.0 and "front_absrel" in m


def test_pack_weights_and_warm_start(tmp_path):
    from monodbh.models.training.common import load_packed_weights, pack_weights
    from monodbh.models.training.tree import train_tree

    data = [fake_tree_sample(0)]
    opts = dict(size="tiny", batch_size=2, crops_per_sample=2, val_n=1, threads=1, mode="sup",
                verbose=False)
    train_tree(tmp_path / "a", 2, data, **opts)
    info = pack_weights(tmp_path / "a", tmp_path / "w.pt")
    assert info["kind"] == "tree" and info["step"] == 2
    w = load_packed_weights(tmp_path / "w.pt", "tree", "tiny")
    wa = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=False)["model"]
    assert all(torch.allclose(w["model"][k], wa[k].float(), rtol=1e-3, atol=1e-3) for k in wa
               if wa[k].is_floating_point())
    with pytest.raises(ValueError, match="tree/tiny"):
        load_packed_weights(tmp_path / "w.pt", "tree", "base")
    # weights packed under the network's old kind are the same network's
    old = torch.load(tmp_path / "w.pt", weights_only=False)
    torch.save({**old, "kind": "treenet"}, tmp_path / "w_old.pt")
    assert load_packed_weights(tmp_path / "w_old.pt", "tree", "tiny")["kind"] == "treenet"
    # a warm-started run begins from the packed weights (lr 0: one step changes nothing)
    train_tree(tmp_path / "b", 1, data, init_weights=str(tmp_path / "w.pt"), lr_g=0.0, **opts)
    wb = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=False)["model"]
    assert all(torch.allclose(wb[k].float(), w["model"][k], atol=1e-6) for k in wb if wb[k].is_floating_point()
               and "running" not in k)
    cfg = json.loads((tmp_path / "b" / "config.json").read_text())
    assert cfg["init_weights"]["from_step"] == 2
