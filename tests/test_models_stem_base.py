"""Stem-base network: ground-truth labels, ONNX export, training smoke run, hooks (the runtime:
test_models_runtime_stem_base)."""
import json

import numpy as np
import pytest
import torch

from monodbh.models.modeling import build
from monodbh.models.runtime.stem_base import STRIP_H, STRIP_ROWS_PER_W, STRIP_W


def fake_base_sample(seed=0, W=160, H=240, dist=4.0, r=0.15, cam_h=1.5, hide_base=False, bush_h_m=0.6):
    """A level camera ``cam_h`` m above flat ground; one vertical round stem of radius ``r`` at
    ``dist`` m straight ahead. The stem's front contact with the ground is at row
    ``cy + f cam_h / (dist - r)``; ``hide_base`` puts a bush 1 m in front of it that hides the
    stem up to ``bush_h_m`` above the ground."""
    rng = np.random.default_rng(seed)
    f, cx, cy = 200.0, W / 2 - 0.5, H / 2 - 0.5
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    depth = np.where(v > cy + 1, cam_h * f / np.maximum(v - cy, 1e-6), 0.0)   # ground (0 = sky)
    x = (u - cx) * dist / f
    on = np.abs(x) <= r
    # the stem stands on the ground: its pixels are those above its base row
    z_front = dist - np.sqrt(np.clip(r * r - x * x, 0, None))
    v_base = cy + f * cam_h / z_front
    stem = on & (v <= v_base)
    depth = np.where(stem, z_front, depth)
    rgb = rng.integers(0, 40, (H, W, 3)).astype(np.uint8)
    rgb[depth > 0] += np.array([60, 90, 30], np.uint8)          # ground: greenish
    rgb[stem] = np.array([120, 90, 60], np.uint8) + rng.integers(0, 20, (int(stem.sum()), 3)).astype(np.uint8)
    vb = cy + f * cam_h / (dist - r)
    if hide_base:
        bush = (np.abs(u - cx) < 3 * r * f / dist) & (v > vb - f * bush_h_m / dist) & (v < vb + 12)
        depth[bush] = dist - 1.0
        rgb[bush] = (20, 120, 20)
    tree = {"id": 1, "dbh_m": 2 * r, "r_bh_m": r, "position_world": [0.0, dist, 0.0],
            "axis_world": [0, 0, 1], "taper": 0.0, "flare": 0.0, "distance_m": dist}
    meta = {"K": [[f, 0, cx], [0, f, cy], [0, 0, 1]], "dist": [0.0] * 5, "width": W, "height": H,
            "R_world_from_cam": [[1, 0, 0], [0, 0, 1], [0, -1, 0]], "t_world_from_cam": [0, 0, cam_h],
            "trees": [tree], "roped_tree": 1}
    return {"rgb": rgb, "depth": depth.astype(np.float32), "meta": meta}, vb


def test_ground_truth_strip_label_is_the_base_row():
    from monodbh.models.training.stem_base import StemBaseTrainConfig, tree_strips

    s, vb = fake_base_sample()
    ex = tree_strips(s, None, StemBaseTrainConfig(), 1)
    assert len(ex) == 1 and ex[0]["roped"]
    f, r, dist = 200.0, 0.15, 4.0
    top_v = 119.5 + f * (1.5 - 1.3) / dist
    width = 2 * f * r / dist
    assert ex[0]["width_px"] == pytest.approx(width, rel=1e-6)
    assert ex[0]["row"] == pytest.approx((vb - top_v) / (width / STRIP_ROWS_PER_W), abs=0.05)
    # the strip shows the stem above its label row and the ground below it
    st = ex[0]["strip"].astype(float)
    k = int(ex[0]["row"])
    assert st[k - 5, STRIP_W // 2, 0] > st[k + 5, STRIP_W // 2, 0] + 30
    hidden, _ = fake_base_sample(hide_base=True)
    assert tree_strips(hidden, None, StemBaseTrainConfig(), 1)[0]["row"] == -1.0
    # jittered strips keep a consistent label (the base's row on the jittered strip)
    exj = tree_strips(s, np.random.default_rng(0), StemBaseTrainConfig(), 4)
    assert len(exj) == 4 and all(abs(e["row"] - ex[0]["row"]) < 8 for e in exj)


def test_base_in_grass_is_labelled_where_it_is():
    """A foot hidden by clutter lower than ``clutter_height_m`` (grass, litter) is labelled at the
    true contact row; a bush that hides more of the stem, or clutter with the option off, hides it."""
    from monodbh.models.synthetic import base_in_view
    from monodbh.models.training.stem_base import StemBaseTrainConfig, tree_strips

    visible, _ = fake_base_sample()
    grass, _ = fake_base_sample(hide_base=True, bush_h_m=0.2)
    row = tree_strips(visible, None, StemBaseTrainConfig(), 1)[0]["row"]
    assert row > 0
    assert tree_strips(grass, None, StemBaseTrainConfig(), 1)[0]["row"] == pytest.approx(row, abs=1e-6)
    assert tree_strips(grass, None, StemBaseTrainConfig(clutter_height_m=0.0), 1)[0]["row"] == -1.0
    for h, expected in ((0.1, True), (0.2, True), (0.45, False), (0.6, False)):
        s, vb = fake_base_sample(hide_base=True, bush_h_m=h)
        xy = np.array([79.5, vb])
        assert base_in_view(s["meta"], s["meta"]["trees"][0], s["depth"], xy, 15.0, 0.3) is expected, h


def test_stem_base_onnx_matches_torch(tmp_path):
    from monodbh.models.export.onnx_io import export_onnx

    torch.manual_seed(0)
    g = build("stem_base", "tiny").eval()
    assert g(torch.randn(2, 4, STRIP_H, STRIP_W)).shape == (2, STRIP_H + 1)
    res = export_onnx(g, g.spec, tmp_path / "stem_base.onnx", check=True, atol=1e-4)
    assert max(res["max_abs_err"].values()) < 1e-4


def test_train_stem_base_smoke_resume_and_hooks(tmp_path):
    from monodbh.models.modeling import get_spec
    from monodbh.models.training.stem_base import base_metrics, train_stem_base
    from monodbh.models.training.common import ListSource, calibration_inputs, evaluate_kind

    data = [fake_base_sample(i, dist=3.0 + i)[0] for i in range(3)]
    opts = dict(size="tiny", batch_size=4, jitters=2, val_n=1, threads=1, warmup_steps=1, log_every=1,
                verbose=False)
    r = train_stem_base(str(tmp_path / "a"), 2, data, stop_at=1, **opts)
    assert r["step"] == 1 and r["bank"] == 4                 # 2 training samples x 2 jitters
    r = train_stem_base(str(tmp_path / "a"), 2, data, resume=True, verbose=False)
    assert r["step"] == 2 and {"recall", "precision", "score"} <= set(r["val"])
    cfg = json.loads((tmp_path / "a" / "config.json").read_text())
    assert cfg["kind"] == "stem_base" and cfg["train_indices"] == 2
    spec = get_spec("stem_base", "tiny")
    src = ListSource(data)
    feeds = calibration_inputs("stem_base", 2, 0, spec, src)
    assert feeds and feeds[0]["strip"].shape == (1, 4, STRIP_H, STRIP_W)
    g = build("stem_base", "tiny").eval()

    def predict(f):
        with torch.no_grad():
            return {"logits": g(torch.from_numpy(f["strip"])).numpy()}

    m = evaluate_kind("stem_base", predict, 2, 0, spec, src)
    assert spec.metric == "score" and 0.0 <= m["score"] <= 1.0
    # metrics: a perfect answer scores 1, a "no base" answer on a visible base 0
    z = np.full((2, STRIP_H + 1), -30.0)
    z[0, 40] = 5.0
    z[1, -1] = 5.0
    assert base_metrics(z, np.array([40.0, -1.0]))["score"] == 1.0
    assert base_metrics(z[1:], np.array([40.0]))["recall"] == 0.0




def test_true_base_pixel_tells_a_base_in_grass_from_a_hidden_one():
    from monodbh.toolkit.evaluation.taps import true_base_pixel

    for h, status in ((0.2, "in_clutter"), (0.6, "occluded")):
        s, _ = fake_base_sample(hide_base=True, bush_h_m=h)
        assert true_base_pixel(s["meta"], s["depth"])[1] == "occluded"
        assert true_base_pixel(s["meta"], s["depth"], clutter_height_m=0.3)[1] == status
    s, _ = fake_base_sample()
    assert true_base_pixel(s["meta"], s["depth"], clutter_height_m=0.3)[1] == "visible"


def test_effl0_stem_base_trains_its_decoder_on_a_frozen_backbone(tmp_path, monkeypatch):
    """Size ``effl0``: cached features give the same logits as the whole network, the backbone
    stays as loaded (ImageNet's in a real run; here the random one, as the pretrained extra may be
    missing) while the decoder moves, and the ONNX file matches torch."""
    from monodbh.models.export.onnx_io import export_onnx
    from monodbh.models.training import pretrained, stem_base as training

    torch.manual_seed(0)
    net = build("stem_base", "effl0").eval()
    x = torch.randn(2, 4, STRIP_H, STRIP_W)
    x[:, 3] = 1.0
    with torch.no_grad():
        assert torch.allclose(net.decode(net.features(x), x[:, 3:]), net(x), atol=1e-5)
    net.train()
    assert not net.backbone.training and net.lat[0].training
    res = export_onnx(net.eval(), net.spec, tmp_path / "stem_base.onnx", check=True, atol=1e-4)
    assert max(res["max_abs_err"].values()) < 1e-4

    loaded = {}

    def fake_load(backbone, path=None):
        loaded["sd"] = {k: v.clone() for k, v in backbone.state_dict().items()}
        return len(loaded["sd"])
    monkeypatch.setattr(pretrained, "load_efficientnet_lite0", fake_load)
    data = [fake_base_sample(i, dist=3.0 + i)[0] for i in range(3)]
    r = training.train_stem_base(str(tmp_path / "run"), 3, data, size="effl0", batch_size=4, jitters=2,
                                 val_n=1, threads=1, warmup_steps=1, log_every=1, verbose=False)
    assert r["step"] == 3 and "score" in r["val"]
    sd = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)["model"]
    assert all(torch.equal(sd[f"backbone.{k}"], v) for k, v in loaded["sd"].items())
    fresh = build("stem_base", "effl0").state_dict()
    assert not torch.equal(sd["lat.0.weight"], fresh["lat.0.weight"])


def test_ship_net_lists_an_effl0_export_as_the_second_network(tmp_path):
    import onnx

    from monodbh.models.runtime.common import MANIFEST_PATH, MODELS_DIR, SPEC_METADATA_KEY, load_manifest
    from monodbh.models.runtime.stem_base import StemBaseNetFinder
    from monodbh.models.training.stem_base import ship_net

    export = tmp_path / "run" / "export"
    export.mkdir(parents=True)
    model = onnx.load(str(MODELS_DIR / "stem_base_net_int8.onnx"))    # as dbh export writes it: kind stem_base
    for p in model.metadata_props:
        if p.key == SPEC_METADATA_KEY:
            p.value = json.dumps({**json.loads(p.value), "kind": "stem_base"})
    onnx.save(model, str(export / "stem_base_int8.onnx"))
    report = {"kind": "stem_base", "size": "effl0", "threads": 2, "exported_at": "t",
              "training": {"steps": 3, "size": "effl0", "data": {}, "seed": 0},
              "int8": {"recipe": "u8s8_qdq_all", "latency_ms": 4.0, "metrics": {"recall": 0.5}}}
    (export / "report.json").write_text(json.dumps(report))
    models = tmp_path / "models"
    models.mkdir()
    man = json.loads(MANIFEST_PATH.read_text())
    del man["models"]["stem_base_net"]
    (models / "manifest.json").write_text(json.dumps(man))
    ship_net(tmp_path / "run", models)
    entry = load_manifest(models / "manifest.json")["models"]["stem_base_net"]
    assert entry["file"] == "stem_base_net_int8.onnx" and entry["spec"]["kind"] == "stem_base_net"
    assert entry["validation"]["int8"] == {"recall": 0.5}
    assert StemBaseNetFinder(models / entry["file"]).spec["kind"] == "stem_base_net"
    (export / "report.json").write_text(json.dumps({**report, "size": "base"}))
    with pytest.raises(ValueError, match="not an exported stem_base effl0 run"):
        ship_net(tmp_path / "run", models)
