"""Segmenter network, Hungarian loss, metrics and training smoke tests (tiny model, 64x64)."""
import pytest
import json

import numpy as np
import torch

from monodbh.models.modeling import build, get_spec
from monodbh.models.modeling.segmenter import NO_OBJECT, TREE_CLASS, Segmenter
from monodbh.models.export import export_onnx
from monodbh.models.training.segmenter import (SetCriterion, build_targets, evaluate_segmenter,
                                               make_batch, panoptic_quality_stats,
                                               train_segmenter)
from monodbh.models.training.common import ListSource, RunDir


def fake_sample(seed, W=64, H=64):
    """Made-up test scene (not a model): sky above, ground below, a bush, 1-3 rectangular trees."""
    rng = np.random.default_rng(seed)
    sem = np.ones((H, W), np.uint8)
    horizon = int(rng.integers(H // 4, H // 2))
    sem[:horizon] = 0
    yy, xx = np.mgrid[:H, :W]
    cy, cx = rng.integers(horizon, H), rng.integers(0, W)
    sem[(yy - cy) ** 2 + (xx - cx) ** 2 < 36] = 2
    inst = np.zeros((H, W), np.uint16)
    for k in range(1, int(rng.integers(1, 4)) + 1):
        x0, w, y1 = int(rng.integers(0, W - 10)), int(rng.integers(4, 10)), int(rng.integers(horizon + 5, H))
        inst[:y1, x0:x0 + w] = k
        sem[:y1, x0:x0 + w] = 3
    colours = np.array([(120, 170, 230), (110, 90, 60), (60, 140, 50), (80, 60, 40), (200, 50, 50)], float)
    rgb = colours[sem] + 12.0 * inst[..., None] + rng.normal(0, 6, (H, W, 3))
    z = np.zeros((H, W), np.float32)
    return {"rgb": np.clip(rgb, 0, 255).astype(np.uint8), "semantic": sem, "instance": inst,
            "depth": z + 5, "rope": np.zeros((H, W), bool), "z1": z, "z2": z,
            "meta": {"roped_tree": 1, "K": [[50.0, 0, W / 2], [0, 50.0, H / 2], [0, 0, 1]]}}


def test_tiny_segmenter_shapes_and_spec():
    m = build("segmenter", "tiny").eval()
    spec = get_spec("segmenter", "tiny")
    assert m.spec == spec
    assert spec.input_names == ["image"] and spec.output_names == ["class_logits", "mask_logits"]
    with torch.no_grad():
        c, k = m(torch.randn(spec.inputs[0].shape))
        preds = m.forward_all(torch.randn(2, 3, 64, 64))
    assert tuple(c.shape) == spec.outputs[0].shape and c.shape[-1] == NO_OBJECT + 1
    assert tuple(k.shape) == spec.outputs[1].shape == (1, 8, 16, 16)
    assert len(preds) == m.cfg.dec_layers + 1
    x = torch.randn(1, 3, 64, 64)
    with torch.no_grad():       # inference path (pooled features) == training path (pooled masks)
        c1, k1 = m(x)
        c2, k2 = m.forward_all(x)[-1]
    assert torch.allclose(c1, c2, atol=1e-4) and torch.allclose(k1, k2, atol=1e-4)
    base = get_spec("segmenter", "base")
    assert base.inputs[0].shape == (1, 3, 256, 256) and base.outputs[1].shape[-2:] == (64, 64)
    assert get_spec("segmenter", "base").to_dict() == type(base).from_dict(base.to_dict()).to_dict()


def test_attention_bias_guards_fully_masked_rows():
    masks = torch.full((1, 2, 8, 8), -5.0)
    masks[0, 1, :2, :2] = 5.0                       # query 1: one visible key at stride 2
    bias = Segmenter._attn_bias(masks, 2)           # (1, 2, 16)
    assert torch.all(bias[0, 0] == 0)               # all masked -> unmasked (Mask2Former guard)
    assert bias[0, 1, 0] == 0 and torch.all(bias[0, 1, 1:] < -1e3)


def test_onnx_matches_torch_tiny(tmp_path):
    m = build("segmenter", "tiny")
    res = export_onnx(m, m.spec, tmp_path / "seg.onnx", check=True, atol=1e-4, rtol=1e-3)
    assert res["ok"] and max(res["max_abs_err"].values()) < 1e-3


def test_build_targets_things_and_stuff():
    s = fake_sample(3)
    t = build_targets(s["semantic"], s["instance"], (16, 16), min_thing_area=4)
    n_trees = len(np.unique(s["instance"])) - 1
    assert (t["labels"] == TREE_CLASS).sum() == n_trees
    assert set(t["labels"].tolist()) - {TREE_CLASS} <= {0, 1, 2, 4}
    assert t["masks"].shape[1:] == (16, 16) and 0 <= t["masks"].min() and t["masks"].max() <= 1
    # stuff + things partition the image
    assert torch.allclose(t["masks"].sum(0), torch.ones(16, 16), atol=1e-5)


def test_hungarian_loss_decreases_on_toy_batch():
    torch.manual_seed(0)
    m = build("segmenter", "tiny")
    spec = m.spec
    src = ListSource([fake_sample(i) for i in range(2)])
    imgs, tgts = make_batch(src, 0, 2, 0, spec, None)
    crit = SetCriterion()
    opt = torch.optim.AdamW(m.parameters(), lr=2e-3)
    losses = []
    for _ in range(8):
        loss, parts = crit(m.forward_all(imgs), tgts)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(parts["loss"])
    assert set(parts) >= {"loss_ce", "loss_mask", "loss_dice", "loss_aux", "loss"}
    assert losses[-1] < 0.8 * losses[0], losses


def test_pq_and_roped_iou_perfect_prediction():
    s = fake_sample(5)
    # a "predictor" that returns GT as logits (one query per GT segment, rest no-object)
    spec = get_spec("segmenter", "tiny")
    t = build_targets(s["semantic"], s["instance"], (64, 64), min_thing_area=1)
    Q = 12
    cls = np.full((1, Q, NO_OBJECT + 1), -10.0, np.float32)
    cls[0, :, NO_OBJECT] = 10.0
    msk = np.full((1, Q, 64, 64), -10.0, np.float32)
    for q, (lab, mm) in enumerate(zip(t["labels"].tolist(), t["masks"].numpy())):
        cls[0, q, NO_OBJECT] = -10.0
        cls[0, q, lab] = 10.0
        msk[0, q][mm > 0.5] = 10.0
    met = evaluate_segmenter(lambda f: {"class_logits": cls, "mask_logits": msk}, [s], spec)
    assert met["roped_iou"] > 0.99 and met["pq"] > 0.99 and met["pq_things"] > 0.99
    stats = panoptic_quality_stats(np.zeros((64, 64), np.int64), [], s["semantic"], s["instance"])
    assert stats[:, 1].sum() == 0 and stats[:, 3].sum() > 0    # nothing predicted -> all FN


@pytest.mark.slow
def test_train_smoke_writes_run_and_resumes_exactly(tmp_path):
    data = [fake_sample(i) for i in range(4)]
    kw = dict(size="tiny", batch_size=2, val_data=data[:2], n_val=2, val_every=2, ckpt_every=1,
              log_every=1, threads=2, verbose=False, warmup_steps=1)
    a = tmp_path / "a"
    out = train_segmenter(a, steps=3, data=data, stop_at=2, **kw)   # interrupted after 2 steps
    run = RunDir(a)
    cfg = json.loads(run.config_path.read_text())
    assert cfg["kind"] == "segmenter" and cfg["size"] == "tiny" and cfg["steps"] == 3
    assert cfg["seed"] == 0 and cfg["lr"] > 0
    assert run.checkpoint_path.exists() and run.read_log()[-1]["kind"] == "val"
    assert run.load_checkpoint()["step"] == 2
    assert "roped_iou" in out["val"] and out["step"] == 2
    train_segmenter(a, steps=3, data=data, resume=True, **kw)
    b = tmp_path / "b"
    train_segmenter(b, steps=3, data=data, **kw)
    ca, cb = RunDir(a).load_checkpoint(), RunDir(b).load_checkpoint()
    assert ca["step"] == cb["step"] == 3
    for k in ca["model"]:
        assert torch.equal(ca["model"][k], cb["model"][k]), k
    la = [r for r in RunDir(a).read_log() if r["kind"] == "train"]
    lb = [r for r in RunDir(b).read_log() if r["kind"] == "train"]
    assert [r["step"] for r in la] == [r["step"] for r in lb] == [1, 2, 3]
    assert np.allclose([r["loss"] for r in la], [r["loss"] for r in lb])
