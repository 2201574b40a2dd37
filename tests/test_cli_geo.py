"""dbh measure --geojson / --tag-from and the field record of every row, with a fake measure
function (the rope pixel and distance of each photo come from a sidecar file), against tree
positions computed independently with pyproj from the known camera position, heading, the
stem's bearing offset and distance."""
import csv
import json
import math
from pathlib import Path

import pytest
from typer.testing import CliRunner

from geo_photos import exif_for, write_photo
from monodbh.calib import Camera, MonodbhError, save_camera
from monodbh.cli.main import app
from monodbh.toolkit.result import RESULT_FIELDS, MeasureResult

pyproj = pytest.importorskip("pyproj")
GEOD = pyproj.Geod(ellps="WGS84")
FAKE = "test_cli_geo:fake_measure"
W, H, F = 640, 480, 800.0
CX, CY = (W - 1) / 2, (H - 1) / 2

# name, camera lat, lon, heading (true), stem offset right of the axis (deg), horizontal distance (m), orientation
TREES = [
    ("T0101_a.jpg", 61.49751, 23.76102, 12.5, -20.0, 6.2, None),
    ("T0102_a.jpg", -33.86880, 151.20930, 301.0, 14.0, 11.8, None),
    ("T0103_b.jpg", 40.71280, -74.00600, 179.5, 0.0, 3.4, 6),        # portrait phone photo
    ("T0104_b.jpg", -54.80190, -68.30300, 359.0, 25.0, 18.0, None),
    ("T0105_c.jpg", 69.64920, 18.95530, 90.0, -33.0, 42.0, 8),
]


class Session:
    def __init__(self, models_dir=None):
        pass


def fake_measure(path, camera, *, pick_xy=None, want_cloud=False, want_debug=False, session=None, **kw):
    """The row the sidecar ``<photo>.truth.json`` describes (``error``: a MonodbhError)."""
    t = json.loads(Path(path + ".truth.json").read_text())
    if t.get("error"):
        raise MonodbhError(f"{path}: {t['error']}")
    return MeasureResult(photo=path, dbh_cm=31.0, dbh_sigma_cm=1.0, distance_m=t["distance_m"],
                         scale_source="stem_base", flags=["short_arc"], timings_ms={"rope": 1.0},
                         rope_xy=t["rope_xy"], tree_id=1)


def _add(folder: Path, name, lat, lon, heading, offset, dist, orientation, ref="T", exif=True, error=None):
    stored = (W, H)                    # orientation 5-8: shown as H x W, the camera turned with it
    shown_w = H if orientation in (5, 6, 7, 8) else W
    cx = (shown_w - 1) / 2
    x = cx + F * math.tan(math.radians(offset))
    ex = exif_for(lat=lat, lon=lon, alt=112.0, accuracy=3.5, heading=heading, heading_ref=ref,
                  taken="2026:06:01 09:15:00", offset="+03:00", orientation=orientation) if exif else None
    p = write_photo(folder / name, size=stored, exif=ex)
    Path(str(p) + ".truth.json").write_text(json.dumps({"distance_m": dist, "rope_xy": [x, 200.0], "error": error}))
    return str(p)


def truth(lat, lon, heading, offset, dist):
    lo, la, _ = GEOD.fwd(lon, lat, (heading + offset) % 360, dist)
    return la, lo


def off_m(lat, lon, la, lo):
    return GEOD.inv(lon, lat, lo, la)[2]


@pytest.fixture()
def batch(tmp_path):
    cam = tmp_path / "cam.yaml"
    save_camera(Camera([[F, 0, CX], [0, F, CY], [0, 0, 1]], None, (W, H)), cam)
    photos = [_add(tmp_path, *t) for t in TREES]
    return {"dir": tmp_path, "cam": str(cam), "photos": photos}


def run(args):
    return CliRunner().invoke(app, ["measure", *args, "--measure-fn", FAKE])


@pytest.mark.parametrize("workers", [1, 2])
def test_tree_positions_within_half_a_metre(batch, workers):
    d = batch["dir"]
    r = run([*batch["photos"], "--calib", batch["cam"], "--csv", str(d / "r.csv"), "--geojson", str(d / "t.geojson"),
             "--workers", str(workers)])
    assert r.exit_code == 0, r.output
    with open(d / "r.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == list(RESULT_FIELDS)
    fc = json.loads((d / "t.geojson").read_text())
    assert fc["type"] == "FeatureCollection" and len(fc["features"]) == len(TREES)
    for row, feat, (name, lat, lon, heading, offset, dist, _) in zip(rows, fc["features"], TREES):
        la, lo = truth(lat, lon, heading, offset, dist)
        assert off_m(la, lo, float(row["tree_lat_deg"]), float(row["tree_lon_deg"])) < 0.5
        glo, gla = feat["geometry"]["coordinates"]
        assert off_m(la, lo, gla, glo) < 0.5
        assert float(row["stem_bearing_deg"]) == pytest.approx((heading + offset) % 360, abs=0.01)
        assert row["tag"] == Path(name).stem and row["taken_at"] == "2026-06-01T09:15:00+03:00"
        assert float(row["camera_lat_deg"]) == pytest.approx(lat, abs=1e-7)
        assert (row["camera_alt_m"], row["gps_accuracy_m"], row["camera_heading_ref"]) == ("112.0", "3.5", "T")
        p = feat["properties"]
        assert p["photo"] == row["photo"] and p["flags"] == ["short_arc"] and "timings_ms" not in p


def test_missing_exif_magnetic_and_errors(tmp_path):
    cam = tmp_path / "cam.yaml"
    save_camera(Camera([[F, 0, CX], [0, F, CY], [0, 0, 1]], None, (W, H)), cam)
    good = _add(tmp_path, "good.jpg", 45.0, 7.0, 10.0, 5.0, 8.0, None)
    plain = _add(tmp_path, "plain.jpg", 45.0, 7.0, 10.0, 5.0, 8.0, None, exif=False)
    png = _add(tmp_path, "plain.png", 45.0, 7.0, 10.0, 5.0, 8.0, None, exif=False)
    mag = _add(tmp_path, "mag.jpg", 45.0, 7.0, 10.0, 5.0, 8.0, None, ref="M")
    bad = _add(tmp_path, "bad.jpg", 45.0, 7.0, 10.0, 5.0, 8.0, None, error="no red rope found")
    gj = tmp_path / "t.geojson"
    r = run([good, plain, png, mag, bad, "--calib", str(cam), "--json", "--geojson", str(gj)])
    assert r.exit_code == 1, r.output
    rows = {Path(d["photo"]).name: d for d in map(json.loads, r.stdout.splitlines())}
    geo_keys = RESULT_FIELDS[RESULT_FIELDS.index("taken_at"):]
    for name in ("plain.jpg", "plain.png"):
        assert rows[name]["tag"] == "plain" and rows[name]["dbh_cm"] == 31.0
        assert all(rows[name][k] is None for k in geo_keys), rows[name]
    assert rows["mag.jpg"]["camera_heading_ref"] == "M" and rows["mag.jpg"]["stem_bearing_deg"] == 15.0
    assert rows["mag.jpg"]["tree_lat_deg"] is None                     # magnetic: no position
    b = rows["bad.jpg"]
    assert b["error"] and b["tag"] == "bad" and b["camera_lat_deg"] == 45.0 and b["taken_at"]
    assert b["stem_bearing_deg"] is None and b["tree_lat_deg"] is None
    fc = json.loads(gj.read_text())
    assert [Path(f["properties"]["photo"]).name for f in fc["features"]] == ["good.jpg"]


def test_tag_from(batch):
    r = run([*batch["photos"][:2], "--calib", batch["cam"], "--json", "--tag-from", r"T(\d{4})"])
    assert r.exit_code == 0, r.output
    assert [json.loads(ln)["tag"] for ln in r.stdout.splitlines()] == ["0101", "0102"]
    r = run([batch["photos"][0], "--calib", batch["cam"], "--json", "--tag-from", r"plot(\d+)"])
    assert json.loads(r.stdout)["tag"] == "T0101_a"                   # no match: the stem


def test_tag_from_bad_regex(batch):
    r = run([batch["photos"][0], "--calib", batch["cam"], "--tag-from", "T(\\d+"])
    assert r.exit_code == 2 and "--tag-from" in r.output and "Traceback" not in r.output


def test_geojson_refuses_an_input_and_the_csv(batch):
    p = batch["photos"][0]
    before = Path(p).read_bytes()
    r = run([p, "--calib", batch["cam"], "--geojson", p])
    assert r.exit_code == 2 and "--geojson" in r.output and "one of the inputs" in r.output
    r = run([p, "--calib", batch["cam"], "--geojson", batch["cam"]])
    assert r.exit_code == 2
    out = str(batch["dir"] / "same.out")
    r = run([p, "--calib", batch["cam"], "--csv", out, "--geojson", out])
    assert r.exit_code == 2 and "--csv" in r.output
    assert Path(p).read_bytes() == before


def test_geojson_folder_is_an_error(batch):
    r = run([batch["photos"][0], "--calib", batch["cam"], "--geojson", str(batch["dir"])])
    assert r.exit_code == 1 and "is a folder" in r.output and "Traceback" not in r.output
