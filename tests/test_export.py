"""ONNX export, int8 quantisation/benchmark and `dbh export` logic on the tiny segmenter."""
import json

import numpy as np
import onnx
import pytest

from monodbh.models.export import (DEFAULT_RECIPES, TABLE_COLUMNS, QuantRecipe, benchmark,
                                   export_onnx, format_table, quantize_int8, random_feeds,
                                   read_spec, recipes_by_name, search_int8)
from monodbh.models.export.cli_impl import export_run
from monodbh.models.modeling import build, get_spec
from monodbh.models.training.segmenter import train_segmenter


def fake_sample(seed, W=64, H=64):
    """Made-up test scene: sky, ground, rectangular trees (tree 1 is the roped one)."""
    rng = np.random.default_rng(seed)
    sem = np.ones((H, W), np.uint8)
    sem[: H // 3] = 0
    inst = np.zeros((H, W), np.uint16)
    for k in (1, 2):
        x0 = int(rng.integers(0, W - 10))
        inst[: H - 5, x0:x0 + 6] = k
        sem[: H - 5, x0:x0 + 6] = 3
    rgb = np.array([(120, 170, 230), (110, 90, 60), (60, 140, 50), (80, 60, 40), (200, 50, 50)])[sem]
    rgb = np.clip(rgb + rng.normal(0, 5, rgb.shape), 0, 255).astype(np.uint8)
    return {"rgb": rgb, "semantic": sem, "instance": inst, "meta": {"roped_tree": 1}}


@pytest.fixture(scope="module")
def tiny_onnx(tmp_path_factory):
    m = build("segmenter", "tiny")
    p = tmp_path_factory.mktemp("onnx") / "segmenter_fp32.onnx"
    export_onnx(m, m.spec, p)
    return p


def test_spec_embedded_in_onnx(tiny_onnx):
    spec = read_spec(tiny_onnx)
    assert spec == get_spec("segmenter", "tiny")
    g = onnx.load(str(tiny_onnx)).graph
    assert [i.name for i in g.input] == ["image"]
    assert [o.name for o in g.output] == ["class_logits", "mask_logits"]


def test_int8_quantization_runs_and_table_has_columns(tiny_onnx, tmp_path):
    spec = get_spec("segmenter", "tiny")
    feeds = [random_feeds(spec, i) for i in range(3)]
    q = quantize_int8(tiny_onnx, tmp_path / "q.onnx", feeds, spec,
                      QuantRecipe("u8s8", activation_type="uint8"))
    assert read_spec(q) == spec
    assert any(n.op_type == "QuantizeLinear" for n in onnx.load(str(q)).graph.node)
    rows = benchmark(tiny_onnx, {"int8": q}, feeds, n_runs=2, warmup=1,
                     metric_fn=lambda predict: {"m": float(np.mean(predict(feeds[0])["class_logits"] ** 2))},
                     metric="m", tolerance=10.0)
    assert [r["model"] for r in rows] == ["fp32", "int8"]
    for r in rows:
        assert set(TABLE_COLUMNS) <= set(r)
    assert rows[1]["rel_l2"] > 0 and rows[1]["latency_ms"] > 0
    table = format_table(rows, "m")
    header = table.splitlines()[0].split()
    assert header == [c if c != "metric" else "m" for c in TABLE_COLUMNS]


@pytest.mark.slow
def test_search_int8_refuses_and_keeps_best(tiny_onnx, tmp_path):
    spec = get_spec("segmenter", "tiny")
    feeds = [random_feeds(spec, i) for i in range(2)]
    recipes = [DEFAULT_RECIPES[0], QuantRecipe("dyn", mode="dynamic")]
    out = tmp_path / "int8.onnx"
    # the "task metric" punishes any output change: an impossible tolerance rejects every recipe
    ref = {}

    def metric(predict):
        o = predict(feeds[0])["mask_logits"]
        ref.setdefault("x", o)
        return {spec.metric: 1.0 - float(np.abs(o - ref["x"]).mean())}

    res = search_int8(tiny_onnx, out, feeds, feeds, spec, metric_fn=metric, recipes=recipes,
                      tolerance=-1.0, n_runs=2, verbose=False)
    assert res["chosen"] is None and not out.exists()
    res = search_int8(tiny_onnx, out, feeds, feeds, spec, metric_fn=metric, recipes=recipes,
                      tolerance=1.0, n_runs=2, verbose=False)
    assert res["chosen"] in {DEFAULT_RECIPES[0].name, "dyn"} and out.exists()
    assert [r["model"] for r in res["rows"]] == ["fp32", DEFAULT_RECIPES[0].name, "dyn"]


def test_recipes_by_name_pins_the_search():
    rs = recipes_by_name(["u8s8_qdq_conv_gemm", "dynamic_matmul", "u8s8_qdq_conv_gemm"])
    assert [r.name for r in rs] == ["u8s8_qdq_conv_gemm", "dynamic_matmul"]
    assert all(r in DEFAULT_RECIPES for r in rs)
    with pytest.raises(ValueError, match="fp4.*known: u8s8_qdq_all"):
        recipes_by_name(["fp4"])


@pytest.mark.slow
def test_export_run_writes_report_and_ships(tmp_path):
    data = [fake_sample(i) for i in range(3)]
    run = tmp_path / "run"
    train_segmenter(run, steps=1, data=data, size="tiny", batch_size=1, val_data=data, n_val=1,
                    verbose=False, threads=2)
    models = tmp_path / "models"
    rep = export_run(run, ship=True, n_calib=2, tolerance=1e6, max_rel_l2=1e6, n_runs=2,
                     models_dir=models,
                     recipes=[QuantRecipe("dyn", mode="dynamic")], data=data, val_data=data,
                     verbose=False)
    assert (run / "export" / "segmenter_fp32.onnx").exists()
    assert (run / "export" / "segmenter_int8.onnx").exists()
    saved = json.loads((run / "export" / "report.json").read_text())
    assert saved["int8"]["recipe"] == "dyn" and "roped_iou" in saved["fp32"]["metrics"]
    assert rep["int8"]["latency_ms"] > 0 and "table" in rep["quantization"]
    man = json.loads((models / "manifest.json").read_text())
    e = man["models"]["segmenter"]
    assert (models / e["file"]).exists() and len(e["sha256"]) == 64
    assert e["inputs"][0] == {"name": "image", "shape": [1, 3, 64, 64], "dtype": "float32"}
    assert e["classes"][3] == "tree" and e["training"]["steps"] == 1
    assert e["training"]["augment"] == json.loads((run / "config.json").read_text())["aug"]
    assert set(e["validation"]) == {"fp32", "int8"} and e["latency_ms"]["int8"] > 0
    assert e["preprocess"][0]["mean"] == pytest.approx([0.485, 0.456, 0.406])
    # exporting again scores the shipped model on the same data first (equal: shipped again)
    rep2 = export_run(run, ship=True, n_calib=2, tolerance=1e6, max_rel_l2=1e6, n_runs=2,
                      models_dir=models, recipes=[QuantRecipe("dyn", mode="dynamic")], data=data,
                      val_data=data, verbose=False)
    assert rep2["previous"]["sha256"] == e["sha256"]
    assert rep2["previous"]["metrics"]["roped_iou"] == pytest.approx(rep2["int8"]["metrics"]["roped_iou"])
    assert rep2["shipped"] is not None
    # an impossible tolerance: nothing shipped, user error, report still written
    from monodbh.calib.errors import MonodbhError

    with pytest.raises(MonodbhError, match="nothing shipped"):
        export_run(run, ship=True, n_calib=2, tolerance=-1.0, n_runs=2, models_dir=tmp_path / "m2",
                   recipes=[QuantRecipe("dyn", mode="dynamic")], data=data, val_data=data,
                   verbose=False)
    assert not (tmp_path / "m2" / "manifest.json").exists()
    assert json.loads((run / "export" / "report.json").read_text())["int8"] is None


def test_ship_model_writes_an_old_kind_manifest_under_todays_kinds(tmp_path):
    """Shipping into a manifest of the networks' old kinds rewrites it under today's (no network
    listed twice), its error model's networks too."""
    from monodbh.models.export.cli_impl import ship_model

    models = tmp_path / "models"
    models.mkdir()
    old = {"format": 1, "models": {"cden": {"file": "cden_int8.onnx", "sha256": "d", "spec": {"kind": "cden"}},
                                   "segmenter": {"file": "segmenter_int8.onnx", "sha256": "s"}},
           "error_model": {"sigma": {"network": 0.3}, "models": {"cden": "d", "segmenter": "s"}}}
    (models / "manifest.json").write_text(json.dumps(old))
    (tmp_path / "new.onnx").write_bytes(b"not a real model")
    ship_model("segmenter", tmp_path / "new.onnx", get_spec("segmenter", "tiny"), {}, models_dir=models)
    man = json.loads((models / "manifest.json").read_text())
    assert set(man["models"]) == {"depth", "segmenter"} and man["models"]["depth"]["spec"]["kind"] == "depth"
    assert man["models"]["segmenter"]["file"] == "segmenter_int8.onnx"
    assert man["error_model"]["models"] == {"depth": "d", "segmenter": "s"}
