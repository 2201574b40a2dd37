"""dbh measure: JSON lines, CSV, out-dir, exit codes, robustness (with a fake measure function)."""
import csv
import json

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from monodbh.calib import Camera, MonodbhError, load_photo, save_camera
from monodbh.cli.main import app
from monodbh.toolkit.result import RESULT_FIELDS, MeasureResult, PointCloud

FAKE = "test_cli_measure:fake_measure"
W, H = 96, 64
CALLS = []  # (photo, csv rows seen before the call), for the incremental-CSV test
CSV_WATCH = {}


class Session:
    """Fake session (picked up automatically as the function module's Session)."""

    def __init__(self, models_dir=None):
        self.models_dir = models_dir


def fake_measure(path, camera, *, pick_xy=None, want_cloud=False, want_debug=False, session=None, base_xy=None,
                 rope_diameter_m=None):
    """Stand-in for toolkit.pipeline.measure_photo: black photo -> no rope; 'boom' -> crash."""
    assert isinstance(session, Session)
    if CSV_WATCH.get("path"):
        with open(CSV_WATCH["path"]) as f:
            CALLS.append((path, len(list(csv.reader(f))) - 1))
        if len(CALLS) == CSV_WATCH.get("interrupt_at"):
            raise KeyboardInterrupt
    if "boom" in path:
        raise RuntimeError("kaput\nsecond line")
    img = load_photo(path)  # PhotoError for corrupt files
    if img.mean() < 5:
        raise MonodbhError(f"{path}: no red rope found")
    h, w = img.shape[:2]
    res = MeasureResult(photo=path, dbh_cm=20.0 + img[..., 0].mean() / 25, dbh_sigma_cm=1.2, distance_m=3.25,
                        scale_source="rope", flags=["short_arc"], timings_ms={"rope": 1.5, "fit": 2.0},
                        estimates_cm={"circle": 30.1}, rope_xy=list(pick_xy or (w / 2, h / 2)), tree_id=1)
    if base_xy is not None:
        res.flags.append(f"base_{base_xy[0]:g}_{base_xy[1]:g}")
    if rope_diameter_m is not None:
        res.flags.append(f"rope_{rope_diameter_m:g}")
    if want_debug:
        t = np.linspace(np.pi, 2 * np.pi, 30)
        res.debug.update(image=img[::2, ::2], image_scale=0.5, rope_polyline=[[5, 15], [25, 16], [40, 15]],
                         edges_xy=[[10, 20], [35, 20]], slice_px=[[10, 20], [35, 20]],
                         slice_xy=np.c_[0.15 * np.cos(t), 3 + 0.15 * np.sin(t)], circle=(0, 3, 0.15))
    if want_cloud:
        res.debug["tree_cloud"] = PointCloud(np.ones((5, 3), np.float32), np.zeros((5, 3), np.uint8),
                                             np.ones(5, np.int32))
    return res


@pytest.fixture()
def files(tmp_path):
    cam = tmp_path / "cam.yaml"
    save_camera(Camera([[80.0, 0, W / 2], [0, 80.0, H / 2], [0, 0, 1]], None, (W, H)), cam)
    rng = np.random.default_rng(0)
    good = []
    for i in range(2):
        p = tmp_path / f"tree{i}.jpg"
        Image.fromarray(rng.integers(40, 255, (H, W, 3), dtype=np.uint8)).save(p)
        good.append(str(p))
    bad = tmp_path / "corrupt.jpg"
    bad.write_text("this is not a JPEG")
    black = tmp_path / "norope.png"
    Image.fromarray(np.zeros((H, W, 3), np.uint8)).save(black)
    CALLS.clear()
    CSV_WATCH.clear()
    return {"cam": str(cam), "good": good, "bad": str(bad), "black": str(black), "dir": tmp_path}


def run(args):
    return CliRunner().invoke(app, ["measure", *args, "--measure-fn", FAKE])


def json_lines(out):
    return [json.loads(ln) for ln in out.splitlines() if ln.strip()]


def test_json_line_schema(files):
    r = run([files["good"][0], files["black"], "--calib", files["cam"], "--json"])
    assert r.exit_code == 1, r.output
    ok, bad = json_lines(r.stdout)
    for d in (ok, bad):
        assert list(d) == list(RESULT_FIELDS)
        assert isinstance(d["timings_ms"], dict) and "total" in d["timings_ms"]
        assert isinstance(d["flags"], list)
    assert ok["photo"] == files["good"][0] and ok["error"] is None
    assert isinstance(ok["dbh_cm"], float) and isinstance(ok["dbh_sigma_cm"], float)
    assert ok["distance_m"] == 3.25 and ok["scale_source"] == "rope" and ok["flags"] == ["short_arc"]
    assert bad["dbh_cm"] is None and bad["dbh_sigma_cm"] is None
    assert bad["error"] == f"{files['black']}: no red rope found" and "\n" not in bad["error"]
    assert "Traceback" not in r.output


def test_corrupt_photo_in_the_middle(files):
    out_csv = files["dir"] / "out.csv"
    photos = [files["good"][0], files["bad"], files["good"][1]]
    r = run([*photos, "--calib", files["cam"], "--csv", str(out_csv)])
    assert r.exit_code == 1, r.output
    rows = list(csv.DictReader(out_csv.open()))
    assert [row["photo"] for row in rows] == photos
    assert rows[0]["dbh_cm"] and rows[2]["dbh_cm"] and not rows[0]["error"]
    assert rows[1]["dbh_cm"] == "" and files["bad"] in rows[1]["error"]
    assert json.loads(rows[0]["timings_ms"])["rope"] == 1.5
    assert "±" in r.stdout and "1 failed" in r.stderr and "Traceback" not in r.output


def test_all_good_exit0_and_out_dir(files):
    out = files["dir"] / "out"
    r = run([*files["good"], "--calib", files["cam"], "--out-dir", str(out), "--pick", "40,30"])
    assert r.exit_code == 0, r.output
    for p in files["good"]:
        stem = p.rsplit("/", 1)[1][:-4]
        with Image.open(out / f"{stem}_overlay.png") as im:
            assert im.size == (W // 2, H // 2)  # the debug image's size
        assert (out / f"{stem}_tree.ply").is_file()
    lines = json_lines((out / "results.jsonl").read_text())
    assert [d["rope_xy"] for d in lines] == [[40.0, 30.0]] * 2
    summary = json.loads((out / "summary.json").read_text())
    assert summary["photos"] == 2 and summary["failed"] == 0 and not summary["interrupted"]
    assert not list(out.glob("*.tmp"))


def test_usage_errors_exit2(files):
    r = run([files["good"][0]])
    assert r.exit_code == 2 and "--calib" in r.output
    r = run([files["good"][0], "--calib", files["cam"], "--pick", "12"])
    assert r.exit_code == 2 and "--pick" in r.output
    r = run([files["good"][0], "--calib", files["cam"], "--pick", "a,b"])
    assert r.exit_code == 2
    r = run([files["good"][0], "--calib", files["cam"], "--base", "3"])
    assert r.exit_code == 2 and "--base" in r.output
    # the stem base is a pixel of one photo
    r = run([*files["good"], "--calib", files["cam"], "--base", "10,20"])
    assert r.exit_code == 2 and "one photo" in r.output


def test_base_reaches_the_measure_function(files):
    r = run([files["good"][0], "--calib", files["cam"], "--base", "10,20.5", "--json"])
    assert r.exit_code == 0, r.output
    assert "base_10_20.5" in json_lines(r.stdout)[0]["flags"]


def test_rope_diameter_reaches_the_measure_function_in_metres(files):
    r = run([*files["good"], "--calib", files["cam"], "--rope-mm", "8", "--json"])
    assert r.exit_code == 0, r.output
    assert all("rope_0.008" in row["flags"] for row in json_lines(r.stdout))
    r = run([files["good"][0], "--calib", files["cam"], "--rope-mm", "0.1"])
    assert r.exit_code == 2 and "--rope-mm" in r.output


def test_bad_calib_is_one_line_error(files):
    r = run([files["good"][0], "--calib", str(files["dir"] / "missing.yaml")])
    assert r.exit_code == 1 and r.stderr.startswith("error: ") and "Traceback" not in r.output


def test_csv_written_incrementally_and_kept_on_interrupt(files):
    out_csv = files["dir"] / "out.csv"
    CSV_WATCH.update(path=str(out_csv), interrupt_at=3)
    photos = [files["good"][0], files["good"][1], files["good"][0]]
    r = run([*photos, "--calib", files["cam"], "--csv", str(out_csv), "--out-dir", str(files["dir"] / "o")])
    assert [n for _, n in CALLS] == [0, 1, 2]  # rows on disk before each photo
    assert r.exit_code == 130
    assert len(list(csv.DictReader(out_csv.open()))) == 2
    summary = json.loads((files["dir"] / "o" / "summary.json").read_text())
    assert summary["interrupted"] and summary["photos"] == 2


def test_unexpected_exception_becomes_row(files):
    boom = files["dir"] / "boom.jpg"
    boom.write_bytes((files["dir"] / "tree0.jpg").read_bytes())
    r = run([str(boom), files["good"][0], "--calib", files["cam"], "--json"])
    assert r.exit_code == 1
    first, second = json_lines(r.stdout)
    assert first["error"] == f"{boom}: internal error: RuntimeError: kaput second line" and first["dbh_cm"] is None
    assert second["error"] is None
    assert "Traceback" not in r.output


def test_missing_pipeline_is_a_clean_error(files):
    r = CliRunner().invoke(app, ["measure", files["good"][0], "--calib", files["cam"],
                                 "--measure-fn", "no_such_module_xyz:measure_photo"])
    assert r.exit_code == 1 and r.stderr.startswith("error: cannot import no_such_module_xyz")


def test_workers_keep_order(files):
    photos = [files["good"][0], files["bad"], files["good"][1]]
    r = run([*photos, "--calib", files["cam"], "--json", "--workers", "2"])
    assert r.exit_code == 1, r.output
    lines = json_lines(r.stdout)
    assert [d["photo"] for d in lines] == photos
    assert [d["error"] is None for d in lines] == [True, False, True]
