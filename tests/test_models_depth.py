"""CDEN (Swin encoder + UpBlock decoder): shapes, ONNX export, depth code, training smoke runs."""
import json
import math

import numpy as np
import torch

from monodbh.models.modeling import build
from monodbh.models.modeling.cden import (build_cden_discriminator, code_to_metric,
                                          metric_to_code)
from monodbh.models.modeling.swin import SwinBlock
from monodbh.models.runtime.depth import depth_code_to_metric, metric_to_depth_code


def _fake_sample(seed=0, W=64, H=48):
    rng = np.random.default_rng(seed)
    f = 0.8 * W
    v = np.arange(H)[:, None].repeat(W, 1)
    depth = np.where(v > H // 3, 1.5 * f / np.maximum(v - H // 3 + 1, 1), 0).astype(np.float32)
    inst = np.zeros((H, W), np.uint16)
    inst[:, W // 2 - 4:W // 2 + 4] = 1
    depth[inst == 1] = 3.0
    meta = {"K": [[f, 0, W / 2 - 0.5], [0, f, H / 2 - 0.5], [0, 0, 1]], "dist": [0.0] * 5,
            "width": W, "height": H, "trees": [], "roped_tree": None}
    return {"rgb": rng.integers(0, 255, (H, W, 3), dtype=np.uint8), "depth": depth,
            "instance": inst, "semantic": (inst > 0).astype(np.uint8) * 3,
            "rope": np.zeros((H, W), bool), "z1": np.where(inst > 0, 2.9, 0).astype(np.float32),
            "z2": np.where(inst > 0, 3.1, 0).astype(np.float32), "meta": meta}


def test_cden_tiny_shapes_and_range():
    torch.manual_seed(0)
    g = build("depth", "tiny")
    s = g.spec.inputs[0].shape[-1]
    assert g.spec.input_names == ["image", "mask"] and g.spec.output_names == ["depth_code"]
    x, m = torch.randn(2, 3, s, s), (torch.rand(2, 1, s, s) > 0.5).float()
    y = g(x, m)
    assert y.shape == (2, 1, s, s) and float(y.abs().max()) <= 1.0
    d = build_cden_discriminator("tiny")
    assert d(x, m, y).shape == (2, 1)
    assert g.spec.extra["depth_code"]["d_max_m"] == 100.0


def test_swin_shift_mask_separates_regions():
    blk = SwinBlock(8, (8, 8), heads=2, ws=4, shift=True)
    assert blk.shift == 2 and blk.attn_mask.shape == (4, 16, 16)
    assert float(blk.attn_mask[0].abs().max()) == 0.0      # top-left window: one region
    assert float(blk.attn_mask[-1].min()) < -50            # bottom-right: several regions
    assert SwinBlock(8, (4, 4), heads=2, ws=8, shift=True).shift == 0


def test_cden_onnx_matches_torch(tmp_path):
    from monodbh.models.export.onnx_io import export_onnx

    torch.manual_seed(0)
    g = build("depth", "tiny").eval()
    res = export_onnx(g, g.spec, tmp_path / "depth.onnx", check=True, atol=1e-4)
    assert max(res["max_abs_err"].values()) < 1e-4


def test_depth_code_roundtrip_numpy_and_torch():
    rng = np.random.default_rng(0)
    for fx_net in (180.0, 204.8, 300.0):
        d = rng.uniform(0.5 * fx_net / 204.8, 80.0, (32, 32)).astype(np.float32)
        t = metric_to_depth_code(d, fx_net, 256)
        assert np.all(np.abs(t) <= 1.0)
        np.testing.assert_allclose(depth_code_to_metric(t, fx_net, 256), d, rtol=1e-5)
        tt = metric_to_code(torch.from_numpy(d), fx_net, 256)
        np.testing.assert_allclose(tt.numpy(), t, atol=1e-6)
        np.testing.assert_allclose(code_to_metric(tt, fx_net, 256).numpy(), d, rtol=1e-5)
    # canonical camera: t = -1 / +1 are 0.5 m / 100 m
    assert math.isclose(float(depth_code_to_metric(np.float32(-1), 204.8, 256)), 0.5, rel_tol=1e-6)
    assert math.isclose(float(depth_code_to_metric(np.float32(1), 204.8, 256)), 100.0, rel_tol=1e-5)
    # beyond range: clipped
    assert metric_to_depth_code(np.float32(1e4), 204.8, 256) == 1.0


def test_depth_example_letterbox_and_metrics():
    from monodbh.models.training.depth import depth_example
    from monodbh.models.training.depth_metrics import depth_metrics

    s = _fake_sample()
    ex = depth_example(s, 64)
    assert ex["image"].shape == (3, 64, 64) and ex["mask"].shape == (1, 64, 64)
    assert not ex["valid"][0, :8].any() and not ex["valid"][0, -8:].any()   # letterbox pad
    assert ex["tree"].shape == (1, 64, 64) and set(np.unique(ex["tree"])) <= {0.0, 1.0}
    assert math.isclose(ex["fx_net"], 0.8 * 64)
    m = depth_metrics(ex["depth"][0], ex["depth"][0], ex["valid"][0])
    assert m["absrel"] == 0.0 and m["delta1"] == 1.0 and m["ms_rmse"] == 0.0
    rng = np.random.default_rng(0)
    from monodbh.models.training.common import AugmentConfig
    ex2 = depth_example(s, 64, rng, AugmentConfig(crop_aspect=(1.0, 1.0)), 0.5, 1.0)
    assert ex2["code"].shape == (1, 64, 64) and np.all(np.abs(ex2["code"]) <= 1)


def test_depth_example_feeds_the_segmenter_mask_when_asked(tmp_path):
    import cv2

    from monodbh.models.training.common import AugmentConfig
    from monodbh.models.training.depth import depth_example
    from monodbh.models.training.segmasks import read_segmask, segmask_path

    s = _fake_sample()
    H, W = s["rgb"].shape[:2]
    seg = np.zeros((H, W), bool)
    seg[:, : W // 4] = True                          # a "segmenter mask" unlike the true one
    s["segmask"] = seg
    aug = AugmentConfig(crop=0.0, hflip=0.0, crop_aspect=(1.0, 1.0))
    with_seg = depth_example(s, 64, np.random.default_rng(0), aug, 0.0, 0.0, segmask_prob=1.0)
    without = depth_example(s, 64, np.random.default_rng(0), aug, 0.0, 0.0, segmask_prob=0.0)
    m_seg, m_gt = with_seg["mask"][0] > 0.5, without["mask"][0] > 0.5
    assert not np.array_equal(m_seg, m_gt)
    assert np.array_equal(with_seg["tree"], without["tree"])     # the L1 weight stays the truth's
    # the mask file round trip
    assert read_segmask(tmp_path, 0) is None
    cv2.imwrite(str(segmask_path(tmp_path, 0)), (seg * 255).astype(np.uint8))
    assert np.array_equal(read_segmask(tmp_path, 0), seg)


def test_depth_losses_tree_weight():
    from monodbh.models.training.depth import DepthTrainConfig, depth_losses

    code = torch.zeros(1, 1, 4, 4)
    t = torch.zeros(1, 1, 4, 4)
    t[..., :2] = 1.0                                  # error 1 on the left half only
    tree = torch.zeros(1, 1, 4, 4)
    tree[..., :1] = 1.0                               # a "tree" inside the error half
    b = {"code": code, "valid": torch.ones(1, 1, 4, 4, dtype=torch.bool), "tree": tree}
    plain = DepthTrainConfig(lambda_silog=0, lambda_grad=0, lambda_l1=1.0)
    weighted = DepthTrainConfig(lambda_silog=0, lambda_grad=0, lambda_l1=1.0, tree_weight=3.0)
    lp, lw = depth_losses(t, b, plain), depth_losses(t, b, weighted)
    assert math.isclose(float(lp["total"]), 0.5)
    # weights: 4 tree pixels x 4, 12 others x 1: (4*4*1 + 4*1*1) / (16 + 12) = 20 / 28
    assert math.isclose(float(lw["total"]), 20 / 28, rel_tol=1e-6)
    assert math.isclose(float(lw["l1"]), 0.5) and math.isclose(float(lw["l1_tree"]), 1.0)


def _weights(run):
    return torch.load(run / "checkpoint.pt", weights_only=False)["model"]


def test_train_depth_smoke_and_resume(tmp_path):
    from monodbh.models.training.depth import train_depth

    data = [_fake_sample(i) for i in range(3)]
    opts = dict(size="tiny", batch_size=2, val_n=2, threads=1, lambda_silog=1.0, lambda_grad=1.0,
                warmup_steps=1, log_every=1, verbose=False)
    a, b = tmp_path / "a", tmp_path / "b"
    r = train_depth(a, 3, data, stop_at=2, **opts)       # a time slice of a 3-step run
    assert r["step"] == 2 and r["images_per_s"] > 0
    cfg = json.loads((a / "config.json").read_text())
    assert cfg["kind"] == "depth" and cfg["size"] == "tiny" and cfg["train"]["lambda_silog"] == 1.0
    logs = [json.loads(l) for l in (a / "log.jsonl").read_text().splitlines()]
    assert any(l["kind"] == "train" and "g_gan" in l for l in logs)
    r = train_depth(a, 3, data, resume=True, verbose=False)
    assert r["step"] == 3 and "delta1" in r["val"] and "ms_absrel" in r["val"]
    logs = [json.loads(l) for l in (a / "log.jsonl").read_text().splitlines()]
    assert [l["step"] for l in logs if l["kind"] == "train"] == [1, 2, 3]
    assert any(l["kind"] == "val" for l in logs)
    train_depth(b, 3, data, **opts)
    wa, wb = _weights(a), _weights(b)
    assert all(torch.allclose(wa[k].float(), wb[k].float(), atol=1e-5) for k in wa)


def test_train_depth_no_gan(tmp_path):
    from monodbh.models.training.depth import train_depth

    r = train_depth(tmp_path / "r", 1, [_fake_sample(0)], size="tiny", batch_size=2, val_n=1,
                    threads=1, lambda_gan=0.0, verbose=False)
    assert r["step"] == 1
    assert "disc" not in torch.load(tmp_path / "r" / "checkpoint.pt", weights_only=False)["extra"]


def test_cden_export_hooks():
    from monodbh.models.modeling import get_spec
    from monodbh.models.training.common import ListSource, calibration_inputs, evaluate_kind

    spec = get_spec("depth", "tiny")
    src = ListSource([_fake_sample(i) for i in range(3)])
    feeds = calibration_inputs("depth", 2, 0, spec, src)
    assert len(feeds) == 2 and feeds[0]["image"].shape == (1, 3, 64, 64)
    assert feeds[0]["mask"].shape == (1, 1, 64, 64)
    g = build("depth", "tiny").eval()

    def predict(f):
        with torch.no_grad():
            t = g(torch.from_numpy(f["image"]), torch.from_numpy(f["mask"]))
        return {"depth_code": t.numpy()}

    m = evaluate_kind("depth", predict, 2, 0, spec, src)
    assert spec.metric == "delta1" and 0.0 <= m["delta1"] <= 1.0 and "ms_absrel" in m
