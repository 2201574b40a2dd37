"""dbh eval / dbh bench / dbh reconstruct with fake pipeline functions."""
import json
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from monodbh.calib import Camera, MonodbhError, save_camera
from monodbh.cli.main import app
from monodbh.toolkit.outputs.cloud_io import read_cloud
from monodbh.toolkit.result import MeasureResult, PointCloud

MOD = "test_cli_measure_eval"
W, H = 64, 48


def fake_eval_measure(path, camera, *, pick_xy=None, want_cloud=False, want_debug=False, session=None):
    """Reads the sample's own JSON: GT + 1 cm / GT - 1 cm (sigma 0.8)."""
    meta = json.loads(Path(path).with_suffix(".json").read_text())
    assert camera.image_size == (W, H) and camera.fx == meta["K"][0][0]
    if not meta["roped_tree"]:
        raise MonodbhError(f"{path}: no red rope found")
    true = meta["trees"][meta["roped_tree"] - 1]["dbh_m"] * 100
    off = 1.0 if meta["seed"] % 2 == 0 else -1.0
    return MeasureResult(photo=path, dbh_cm=true + off, dbh_sigma_cm=0.8, distance_m=4.0,
                         scale_source="rope", timings_ms={"segment": 10.0 + meta["seed"], "fit": 1.0})


def fake_gt_measure(path, camera, *, session=None, **kw):
    """A ground-truth measure function: reads the sample's ground truth beside the photo; exact."""
    from monodbh.toolkit.evaluation.synth_samples import read_ground_truth

    assert session is None
    gt = read_ground_truth(path)
    meta = json.loads(Path(path).with_suffix(".json").read_text())
    assert gt["depth"].shape == (H, W) and gt["meta"]["seed"] == meta["seed"]
    if not meta["roped_tree"]:
        raise MonodbhError(f"{path}: no red rope found")
    return MeasureResult(photo=path, dbh_cm=meta["trees"][meta["roped_tree"] - 1]["dbh_m"] * 100,
                         dbh_sigma_cm=0.8, distance_m=4.0)


def fake_reconstruct(path, camera, session=None, pick_xy=None):
    assert pick_xy in (None, (5.0, 6.0))
    if "norope" in path:
        raise MonodbhError(f"{path}: no red rope found")
    xyz = np.array([[0, 0, 5], [1, -1, 6], [0.2, 0.5, 4.5]], np.float32)
    cloud = PointCloud(xyz, np.array([[255, 0, 0], [0, 255, 0], [1, 2, 3]], np.uint8), np.array([0, 3, 7], np.int32))
    return MeasureResult(photo=path, dbh_cm=30.0, dbh_sigma_cm=1.0, distance_m=5.0, tree_id=3), cloud


@pytest.fixture()
def synth_dir(tmp_path):
    rng = np.random.default_rng(1)
    K = [[50.0, 0, W / 2], [0, 50.0, H / 2], [0, 0, 1]]
    roped = [1, 2, None]
    for i, rt in enumerate(roped):
        stem = tmp_path / f"{i:06d}"
        Image.fromarray(rng.integers(0, 255, (H, W, 3), dtype=np.uint8)).save(stem.with_suffix(".jpg"))
        meta = {"seed": i, "width": W, "height": H, "K": K, "dist": [0.01, 0, 0, 0, 0], "roped_tree": rt,
                "trees": [{"id": 1, "dbh_m": 0.30}, {"id": 2, "dbh_m": 0.25}]}
        stem.with_suffix(".json").write_text(json.dumps(meta))
        z = np.zeros((H, W), np.float32)
        np.savez(stem.with_suffix(".npz"), depth=z, semantic=z.astype(np.uint8), instance=z.astype(np.uint16),
                 rope=z.astype(bool), z1=z, z2=z)
    return tmp_path


def test_eval_metrics_and_report(synth_dir, tmp_path):
    rep = tmp_path / "report.json"
    r = CliRunner().invoke(app, ["eval", str(synth_dir), "--json", str(rep), "--measure-fn", f"{MOD}:fake_eval_measure"])
    assert r.exit_code == 0, r.output
    m = json.loads(rep.read_text())["metrics"]
    assert m["roped"] == 2 and m["no_rope"] == 1 and m["detection_rate"] == 1.0
    assert m["mae_cm"] == pytest.approx(1.0) and m["bias_cm"] == pytest.approx(0.0)
    assert m["rmse_cm"] == pytest.approx(1.0) and m["rel_mae_pct"] == pytest.approx((1 / 30 + 1 / 25) * 50)
    assert m["coverage_1sigma"] == 0.0 and m["coverage_2sigma"] == 1.0
    assert m["refusal_rate"] == 1.0 and m["false_measurements"] == 0
    t = json.loads(rep.read_text())["timings_ms"]
    assert t["segment"]["median"] == pytest.approx(10.5) and t["total"]["n"] == 3 and list(t)[-1] == "total"
    assert "MAE" in r.stdout and "segment" in r.stdout


def test_eval_heldout_folder_side_by_side(synth_dir, tmp_path):
    # the same scenes in another look: a copy whose records say "heldout", one photo dropped
    held = tmp_path / "held"
    held.mkdir()
    for i in (0, 1):
        for ext in (".jpg", ".npz"):
            (held / f"{i:06d}{ext}").write_bytes((synth_dir / f"{i:06d}{ext}").read_bytes())
        meta = json.loads((synth_dir / f"{i:06d}.json").read_text())
        (held / f"{i:06d}.json").write_text(json.dumps({**meta, "look": "heldout"}))
    rep = tmp_path / "report.json"
    r = CliRunner().invoke(app, ["eval", str(synth_dir), "--heldout", str(held), "--json", str(rep),
                                 "--measure-fn", f"{MOD}:fake_eval_measure"])
    assert r.exit_code == 0, r.output
    report = json.loads(rep.read_text())
    assert report["look"] == "default" and report["metrics"]["samples"] == 3
    assert report["heldout"]["look"] == "heldout" and report["heldout"]["metrics"]["samples"] == 2
    assert report["heldout"]["metrics"]["roped"] == 2 and report["heldout"]["metrics"]["no_rope"] == 0
    assert "side by side" in r.stdout and "held (heldout)" in r.stdout
    r = CliRunner().invoke(app, ["eval", str(synth_dir), "--heldout", str(tmp_path / "nope"),
                                 "--measure-fn", f"{MOD}:fake_eval_measure"])
    assert r.exit_code == 2 and "nope: no such folder" in r.output


def test_eval_gt_perception_and_limit(synth_dir, tmp_path):
    rep = tmp_path / "report.json"
    r = CliRunner().invoke(app, ["eval", str(synth_dir), "--gt-perception", "--limit", "2", "--json", str(rep),
                                 "--measure-fn", f"{MOD}:fake_gt_measure", "--session-factory", "none"])
    assert r.exit_code == 0, r.output
    m = json.loads(rep.read_text())["metrics"]
    assert m["samples"] == 2 and m["mae_cm"] == pytest.approx(0.0)


def fake_pick_measure(path, camera, *, pick_xy=None, want_cloud=False, want_debug=False, session=None):
    """Measures only at a tap on the rope, and only within 2 px of where the sample's rope is."""
    meta = json.loads(Path(path).with_suffix(".json").read_text())
    if pick_xy is None:
        raise MonodbhError(f"{path}: no red rope found")
    assert abs(pick_xy[0] - 20.0) < 2 and abs(pick_xy[1] - 10.0) < 2, pick_xy
    true = meta["trees"][meta["roped_tree"] - 1]["dbh_m"] * 100
    return MeasureResult(photo=path, dbh_cm=true, dbh_sigma_cm=1.0, distance_m=4.0)


def test_eval_tap_rope_passes_the_rope_pixel_as_pick(synth_dir, tmp_path):
    for i in (0, 1):                          # the roped samples get a visible rope
        stem = synth_dir / f"{i:06d}"
        with np.load(stem.with_suffix(".npz")) as z:
            arr = {k: z[k] for k in z.files}
        arr["rope"][10, 15:26] = True
        np.savez(stem.with_suffix(".npz"), **arr)
    rep = tmp_path / "report.json"
    r = CliRunner().invoke(app, ["eval", str(synth_dir), "--tap-rope", "--tap-noise-px", "0.3", "--json", str(rep),
                                 "--measure-fn", f"{MOD}:fake_pick_measure"])
    assert r.exit_code == 0, r.output
    d = json.loads(rep.read_text())
    assert d["tap_rope"]["tapped"] == 2 and d["metrics"]["detection_rate"] == 1.0
    assert d["metrics"]["mae_cm"] == pytest.approx(0.0) and d["metrics"]["false_measurements"] == 0


def test_reconstruct_ply_las_and_errors(tmp_path):
    cam = tmp_path / "cam.yaml"
    save_camera(Camera([[50.0, 0, W / 2], [0, 50.0, H / 2], [0, 0, 1]], None, (W, H)), cam)
    photo = tmp_path / "p.jpg"
    Image.fromarray(np.full((H, W, 3), 90, np.uint8)).save(photo)
    fn = ["--measure-fn", f"{MOD}:fake_reconstruct"]
    for ext in ("ply", "las"):
        out = tmp_path / f"scene.{ext}"
        r = CliRunner().invoke(app, ["reconstruct", str(photo), "--calib", str(cam), "-o", str(out), *fn])
        assert r.exit_code == 0, r.output
        c = read_cloud(out)
        assert c.tree_id.tolist() == [0, 3, 7] and c.rgb[1].tolist() == [0, 255, 0]
        assert np.allclose(c.xyz[1], [1, -1, 6], atol=1e-3)
        assert "3 points" in r.stderr and "2 trees" in r.stderr
    r = CliRunner().invoke(app, ["reconstruct", str(photo), "--calib", str(cam), "-o", str(tmp_path / "l.ply"),
                                 "--frame", "level", "--pick", "5,6", *fn])
    assert r.exit_code == 0 and np.allclose(read_cloud(tmp_path / "l.ply").xyz[1], [1, 6, 1])
    r = CliRunner().invoke(app, ["reconstruct", str(photo), "--calib", str(cam), "-o", str(tmp_path / "s.xyz"), *fn])
    assert r.exit_code == 2 and "extension" in r.output
    r = CliRunner().invoke(app, ["reconstruct", str(photo), "--calib", str(cam), "-o", str(tmp_path / "w.ply"),
                                 "--frame", "world", *fn])
    assert r.exit_code == 2 and "pose" in r.output
    norope = tmp_path / "norope.jpg"
    norope.write_bytes(photo.read_bytes())
    r = CliRunner().invoke(app, ["reconstruct", str(norope), "--calib", str(cam), "-o", str(tmp_path / "n.ply"), *fn])
    assert r.exit_code == 1 and r.stderr.strip() == f"error: {norope}: no red rope found"
    assert not (tmp_path / "n.ply").exists()


def test_bench_fresh_process(tmp_path, monkeypatch):
    cam = tmp_path / "cam.yaml"
    save_camera(Camera([[50.0, 0, W / 2], [0, 50.0, H / 2], [0, 0, 1]], None, (W, H)), cam)
    photo = tmp_path / "000000.jpg"
    Image.fromarray(np.full((H, W, 3), 90, np.uint8)).save(photo)
    (tmp_path / "000000.json").write_text(json.dumps({"seed": 0, "K": [[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]],
                                                      "roped_tree": 1, "trees": [{"dbh_m": 0.3}]}))
    here = str(Path(__file__).resolve().parent)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([here, os.environ.get("PYTHONPATH", "")]))
    out = tmp_path / "bench.json"
    r = CliRunner().invoke(app, ["bench", str(photo), "--calib", str(cam), "--repeat", "2", "--warmup", "1",
                                 "--json", str(out), "--measure-fn", f"{MOD}:fake_eval_measure",
                                 "--session-factory", "none"])
    assert r.exit_code == 0, r.output
    d = json.loads(out.read_text())
    assert d["repeat"] == 2 and len(d["runs"]) == 3 and d["stages_ms"]["segment"] == pytest.approx(10.0)
    assert 0 < d["import_s"] < d["startup_s"] and d["peak_mib"] > 10 and set(d["pass"]) == {"startup_s", "per_photo_s", "peak_mib"}
    assert "start-up" in r.stdout and "peak memory" in r.stdout
    # without --calib, a dbh synth photo's camera comes from its .json; other photos are an error
    meta = json.loads((tmp_path / "000000.json").read_text())
    (tmp_path / "000000.json").write_text(json.dumps({**meta, "width": W, "height": H}))
    r = CliRunner().invoke(app, ["bench", str(photo), "--repeat", "1", "--warmup", "0",
                                 "--measure-fn", f"{MOD}:fake_eval_measure", "--session-factory", "none"])
    assert r.exit_code == 0, r.output
    other = tmp_path / "other.jpg"
    other.write_bytes(photo.read_bytes())
    r = CliRunner().invoke(app, ["bench", str(other), "--measure-fn", f"{MOD}:fake_eval_measure",
                                 "--session-factory", "none"])
    assert r.exit_code == 1 and "no --calib given" in r.output
