"""Rope verifier: the network, training, export hooks, its examples from rendered scenes (the runtime:
test_models_runtime_rope_verifier)."""
import json

import numpy as np
import pytest
import torch

from monodbh.models.modeling import build
from monodbh.models.runtime.rope_verifier import N_SIDE, PATCH_H, PATCH_W, band_patch
from test_models_runtime_rope_verifier import _stem_photo


def test_rope_verifier_onnx_matches_torch(tmp_path):
    from monodbh.models.export.onnx_io import export_onnx

    torch.manual_seed(0)
    g = build("rope_verifier", "tiny").eval()
    assert g(torch.randn(2, 5, PATCH_H, PATCH_W), torch.randn(2, N_SIDE)).shape == (2, 1)
    res = export_onnx(g, g.spec, tmp_path / "rope_verifier.onnx", check=True, atol=1e-4)
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


def test_train_rope_verifier_smoke_resume_metrics_and_hooks(tmp_path):
    from monodbh.models.modeling import get_spec
    from monodbh.models.training.common import calibration_inputs, evaluate_kind, make_source
    from monodbh.models.training.rope_verifier import rope_metrics, train_rope_verifier

    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    _fake_bank(a, seed=0)
    _fake_bank(b, seed=1)
    opts = dict(size="tiny", batch_size=8, threads=1, warmup_steps=1, log_every=1, val_every=1, verbose=False)
    r = train_rope_verifier(str(tmp_path / "run"), 2, [str(a)], val_data=[str(b)], stop_at=1, **opts)
    assert r["step"] == 1 and r["bank"] == 24
    r = train_rope_verifier(str(tmp_path / "run"), 2, resume=True, verbose=False)
    assert r["step"] == 2 and {"auc", "top1"} <= set(r["val"])
    cfg = json.loads((tmp_path / "run" / "config.json").read_text())
    assert cfg["kind"] == "rope_verifier" and cfg["data"]["type"] == "banks"
    src = make_source([str(b)])
    spec = get_spec("rope_verifier", "tiny")
    feeds = calibration_inputs("rope_verifier", 6, 0, spec, src)
    assert len(feeds) == 6 and feeds[0]["patch"].shape == (1, 5, PATCH_H, PATCH_W)
    assert feeds[0]["side"].shape == (1, N_SIDE)
    g = build("rope_verifier", "tiny").eval()

    def predict(f):
        with torch.no_grad():
            return {"logit": g(torch.from_numpy(f["patch"]), torch.from_numpy(f["side"])).numpy()}

    m = evaluate_kind("rope_verifier", predict, 6, 0, spec, src)
    assert 0.0 <= m["auc"] <= 1.0
    # metrics: logits that rank every rope band first give AUC 1 and top-1 1
    bank = src.arrays
    z = bank["label"].astype(float) * 5.0
    mm = rope_metrics(z, bank)
    assert mm["auc"] == 1.0 and mm["top1"] == 1.0 and mm["n_missed_by_band"] == 6
    assert rope_metrics(-z, bank)["top1"] == 0.0
    with pytest.raises(ValueError, match="npz"):
        train_rope_verifier(str(tmp_path / "run2"), 1, [{"a": 1}], **opts)


def test_collect_patches_labels_the_rope_row_of_a_rendered_scene(tmp_path):
    pytest.importorskip("embreex")
    from monodbh.models.synthetic import generate_sample
    from monodbh.models.synthetic.io import write_sample
    from monodbh.toolkit.evaluation.fit_rope_stem import collect_patches

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
