"""dbh measure --resume: a run killed half-way, resumed, gives the CSV of one uninterrupted run."""
import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from monodbh.calib import Camera, save_camera
from monodbh.toolkit.result import RESULT_FIELDS, MeasureResult

HERE = Path(__file__).resolve().parent
FN = "test_cli_measure_resume:steady_measure"
_RUN_DBH = "import sys; from monodbh.cli.main import main; sys.argv[0] = 'dbh'; main()"


def steady_measure(path, camera, **kw):
    """A deterministic stand-in for measure_photo; ``MONODBH_TEST_HANG=name`` hangs on that photo."""
    name = Path(path).name
    if os.environ.get("MONODBH_TEST_HANG") == name:
        time.sleep(120)
    if "bad" in name:
        return MeasureResult(photo=path, error=f"{path}: no red rope found", timings_ms={"total": 1.0})
    k = int(name.split("_")[1].split(".")[0])
    return MeasureResult(photo=path, dbh_cm=20.0 + k / 7, dbh_sigma_cm=1.5, distance_m=3.0 + k / 11,
                         scale_source="stem_base", flags=["short_arc"] if k % 2 else [],
                         timings_ms={"total": 10.0 + k}, estimates_cm={"tangent": 20.0 + k}, rope_xy=[5.0, 6.0],
                         tree_id=k)


def _dbh(args, cwd, env=None):
    e = {**os.environ, "PYTHONPATH": os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")]),
         **(env or {})}
    return subprocess.Popen([sys.executable, "-c", _RUN_DBH, *args], cwd=cwd, env=e,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.fixture()
def batch(tmp_path):
    W, H = 96, 64
    save_camera(Camera([[80.0, 0, W / 2], [0, 80.0, H / 2], [0, 0, 1]], None, (W, H)), tmp_path / "cam.yaml")
    (tmp_path / "photos").mkdir()
    names = [f"p_{k:02d}.jpg" for k in range(8)]
    names[3] = "p_03_bad.jpg"
    for n in names:
        Image.fromarray(np.full((H, W, 3), 120, np.uint8)).save(tmp_path / "photos" / n)
    return tmp_path, sorted(names)


def _rows(p):
    with open(p, newline="") as f:
        return list(csv.reader(f))


def test_resume_after_a_kill_gives_the_uninterrupted_csv(batch):
    d, names = batch
    args = ["measure", "photos", "--calib", "cam.yaml", "--measure-fn", FN, "--session-factory", "none"]
    full = _dbh(args + ["--csv", "full.csv"], d)
    full.communicate(timeout=120)
    assert full.returncode == 1                      # one photo has no rope
    # killed while measuring the 6th photo: 5 rows on disk
    hang = _dbh(args + ["--csv", "part.csv", "--out-dir", "out"], d, {"MONODBH_TEST_HANG": names[5]})
    deadline = time.time() + 60
    while time.time() < deadline and len(_rows(d / "part.csv") if (d / "part.csv").exists() else []) < 6:
        time.sleep(0.05)
    time.sleep(0.3)
    hang.send_signal(signal.SIGKILL)
    hang.communicate(timeout=30)
    part = _rows(d / "part.csv")
    assert len(part) == 6 and part[0] == list(RESULT_FIELDS)
    # a half-written last line, as a kill in the middle of a write would leave
    with open(d / "part.csv", "a") as f:
        f.write("photos/p_05.jpg,21.")
    res = _dbh(args + ["--csv", "part.csv", "--out-dir", "out", "--resume"], d)
    out, err = res.communicate(timeout=120)
    assert res.returncode == 1, err
    assert "5 of 8 photos already in part.csv: kept (--resume)" in err
    assert _rows(d / "part.csv") == _rows(d / "full.csv")
    lines = (d / "out" / "results.jsonl").read_text().splitlines()
    assert [l.split('"photo": "')[1].split('"')[0] for l in lines] == [f"photos/{n}" for n in names]
    # nothing left to do: the CSV is kept as it is
    again = _dbh(args + ["--csv", "part.csv", "--resume"], d)
    again.communicate(timeout=120)
    assert _rows(d / "part.csv") == _rows(d / "full.csv")


def test_resume_needs_a_csv_of_this_version(batch, tmp_path):
    d, _ = batch
    args = ["measure", "photos", "--calib", "cam.yaml", "--measure-fn", FN, "--session-factory", "none"]
    p = _dbh(args + ["--resume"], d)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 2 and "--resume needs --csv" in err
    (d / "other.csv").write_text("a,b\n1,2\n")
    p = _dbh(args + ["--resume", "--csv", "other.csv"], d)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 1 and err.strip() == ("error: other.csv: not a results CSV of this version (its "
                                                "columns differ); give another --csv to resume into, or leave "
                                                "out --resume")
    assert (d / "other.csv").read_text() == "a,b\n1,2\n"


def test_resumed_rows_keep_their_types_and_trees(tmp_path):
    import json

    from monodbh.toolkit.outputs.results_file import ResultWriter

    row = MeasureResult(photo="a.jpg", dbh_cm=25.0, dbh_sigma_cm=1.0, distance_m=4.0, tag="a",
                        camera_lat_deg=48.1, camera_lon_deg=11.5, tree_lat_deg=48.10003, tree_lon_deg=11.50002,
                        timings_ms={"total": 3.0})
    with ResultWriter(csv_path=tmp_path / "r.csv", out_dir=tmp_path / "o") as w:
        w.add(row)
        w.finish()
    first = (tmp_path / "o" / "results.jsonl").read_text()
    with ResultWriter(csv_path=tmp_path / "r.csv", out_dir=tmp_path / "o", resume=True,
                      geojson_path=tmp_path / "t.geojson") as w:
        assert list(w.done) == ["a.jpg"]
        w.finish()
    assert (tmp_path / "o" / "results.jsonl").read_text() == first
    feats = json.loads((tmp_path / "t.geojson").read_text())["features"]
    assert len(feats) == 1 and feats[0]["geometry"]["coordinates"] == [11.50002, 48.10003]
