"""Rope-band verifier: patch cutting, the network, training, export hooks, the shipped model."""
import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from monodbh.models.modeling import build
from monodbh.models.runtime_rope import (N_SIDE, PATCH_H, PATCH_W, band_patch, patch_feed, patch_geometry,
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


def test_ropenet_onnx_matches_torch(tmp_path):
    from monodbh.models.export.onnx_io import export_onnx

    torch.manual_seed(0)
    g = build("ropenet", "tiny").eval()
    assert g(torch.randn(2, 5, PATCH_H, PATCH_W), torch.randn(2, N_SIDE)).shape == (2, 1)
    res = export_onnx(g, g.spec, tmp_path / "ropenet.onnx", check=True, atol=1e-4)
    assert max(res["max_abs_err"].values()) < 1e-4


def _fake_bank(path, n=24, seed=0):
    rng = np.random.default_rng(seed)
    img, mask = _stem_photo()
    acc = {k: [] for k in ("patch", "stem", "inside", "side", "label", "score", "trunk_like", "photo", "roped",
                           "found_by_band")}
    for i in range(n):
        lab = i % 3 == 0
        y = 60.0 if lab else float(rng.uniform(20, 140))
        p, st, ins = band_patch(img, mask, (100.0, y), (1.0, 0.0), 40.0)
        for k, v in (("patch", p), ("stem", st), ("inside", ins), ("side", rng.normal(size=N_SIDE).astype(np.float32)),
                     ("label", int(lab)), ("score", 0.0), ("trunk_like", True), ("photo", i // 3),
                     ("roped", i // 3 < 6), ("found_by_band", False)):
            acc[k].append(v)
    arr = {k: np.asarray(v) for k, v in acc.items()}
    arr["side"] = arr["side"].astype(np.float32)
    arr["label"] = arr["label"].astype(np.uint8)
    np.savez(path, **arr)
    return arr


def test_train_ropenet_smoke_resume_metrics_and_hooks(tmp_path):
    from monodbh.models.modeling import get_spec
    from monodbh.models.training.common import calibration_inputs, evaluate_kind, make_source
    from monodbh.models.training.ropenet import rope_metrics, train_ropenet

    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    _fake_bank(a, seed=0)
    _fake_bank(b, seed=1)
    opts = dict(size="tiny", batch_size=8, threads=1, warmup_steps=1, log_every=1, val_every=1, verbose=False)
    r = train_ropenet(str(tmp_path / "run"), 2, [str(a)], val_data=[str(b)], stop_at=1, **opts)
    assert r["step"] == 1 and r["bank"] == 24
    r = train_ropenet(str(tmp_path / "run"), 2, resume=True, verbose=False)
    assert r["step"] == 2 and {"auc", "top1"} <= set(r["val"])
    cfg = json.loads((tmp_path / "run" / "config.json").read_text())
    assert cfg["kind"] == "ropenet" and cfg["data"]["type"] == "banks"
    src = make_source([str(b)])
    spec = get_spec("ropenet", "tiny")
    feeds = calibration_inputs("ropenet", 6, 0, spec, src)
    assert len(feeds) == 6 and feeds[0]["patch"].shape == (1, 5, PATCH_H, PATCH_W)
    assert feeds[0]["side"].shape == (1, N_SIDE)
    g = build("ropenet", "tiny").eval()

    def predict(f):
        with torch.no_grad():
            return {"logit": g(torch.from_numpy(f["patch"]), torch.from_numpy(f["side"])).numpy()}

    m = evaluate_kind("ropenet", predict, 6, 0, spec, src)
    assert 0.0 <= m["auc"] <= 1.0
    # metrics: logits that rank every rope band first give AUC 1 and top-1 1
    bank = src.arrays
    z = bank["label"].astype(float) * 5.0
    mm = rope_metrics(z, bank)
    assert mm["auc"] == 1.0 and mm["top1"] == 1.0 and mm["n_missed_by_band"] == 6
    assert rope_metrics(-z, bank)["top1"] == 0.0
    with pytest.raises(ValueError, match="npz"):
        train_ropenet(str(tmp_path / "run2"), 1, [{"a": 1}], **opts)


def test_shipped_rope_verifier_prefers_the_rope_row():
    from monodbh.models.runtime import load_manifest
    from monodbh.models.runtime_rope import RopeVerifier

    if "ropenet" not in load_manifest().get("models", {}):
        pytest.skip("no shipped rope verifier")
    ver = RopeVerifier(threads=1)
    img, mask = _stem_photo(rope_rgb=(135, 95, 85))           # faint rope
    feats = {"log_contrast": np.log(0.03), "log_zpix": np.log(6.0), "log_zprof": np.log(8.0),
             "log_width": np.log(41.0), "red_shift": 0.8}
    bands = [SimpleNamespace(center_xy=(100.0, y), direction=(1.0, 0.0), width_px=41, features=feats)
             for y in (60.0, 110.0)]
    z = ver.logits(img, [mask, mask], bands)
    assert z.shape == (2,) and z[0] > z[1]


def test_collect_patches_labels_the_rope_row_of_a_rendered_scene(tmp_path):
    pytest.importorskip("embreex")
    from monodbh.models.synthetic import generate_sample
    from monodbh.models.synthetic.io import write_sample
    from monodbh.toolkit.fit_rope_stem import collect_patches

    folder = tmp_path / "synth"
    for i in range(2):
        write_sample(folder, i, generate_sample(9000, i, (640, 480)))
    out = tmp_path / "bank" / "b.npz"
    arr = collect_patches(str(folder), str(out), verbose=False)
    assert out.exists()
    n = len(arr["label"])
    assert n > 0 and arr["patch"].shape == (n, PATCH_H, PATCH_W, 3) and arr["side"].shape == (n, N_SIDE)
    assert set(np.unique(arr["photo"])) <= {0, 1} and arr["label"].max() <= 1
    # a labelled row lies on a roped photo
    assert not (arr["label"].astype(bool) & ~arr["roped"]).any()
