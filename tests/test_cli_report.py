"""dbh measure --report, opened in headless Chromium: every photo listed, thumbnails shown, the
histogram and the map drawn, sorting; a 200-photo batch under 20 MB, loaded in under 2 s."""
import json
import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from browser import body_data, dump_dom, require_chromium, screenshot
from geo_photos import exif_for, write_photo
from monodbh.calib import Camera, MonodbhError, save_camera
from monodbh.cli.main import app
from monodbh.toolkit.outputs.stand import dbh_classes
from monodbh.toolkit.result import MeasureResult

FAKE = "test_cli_report:fake_measure"
W, H, F = 640, 480, 800.0
LAT0, LON0 = 61.49751, 23.76102
BAR = np.array([46, 125, 50])                     # .bar fill #2e7d32
TREE = np.array([96, 156, 98])                    # .tree fill at 0.75 over the map's #f6f9f4


class Session:
    def __init__(self, models_dir=None):
        pass


def fake_measure(path, camera, *, pick_xy=None, want_cloud=False, want_debug=False, session=None, **kw):
    """The row the sidecar ``<photo>.truth.json`` describes (``error``: a MonodbhError)."""
    t = json.loads(Path(path + ".truth.json").read_text())
    if t.get("error"):
        raise MonodbhError(f"{path}: {t['error']}")
    return MeasureResult(photo=path, dbh_cm=t["dbh_cm"], dbh_sigma_cm=1.2, distance_m=t["distance_m"],
                         scale_source=t["scale"], flags=t["flags"], timings_ms={"rope": 1.0},
                         rope_xy=[W / 2, 200.0], tree_id=1)


def _photo(folder: Path, name: str, k: int, *, exif: bool = True, error=None, size=(W, H)) -> str:
    rng = np.random.default_rng(k)
    lat = LAT0 + rng.uniform(-2e-4, 2e-4)
    lon = LON0 + rng.uniform(-4e-4, 4e-4)
    ex = exif_for(lat=lat, lon=lon, alt=110.0, accuracy=4.0, heading=float(rng.uniform(0, 360)),
                  taken=f"2026:06:01 09:{k % 60:02d}:00") if exif else None
    p = write_photo(folder / name, size=size, exif=ex, seed=k)
    scale = "stem_base" if k % 3 else "network+ground_plane"
    flags = ["short_arc"] if k % 3 else ["scale_from_network", "distance_calibrated"]
    Path(str(p) + ".truth.json").write_text(json.dumps(
        {"dbh_cm": round(12 + (k * 7.3) % 45, 1), "distance_m": 3 + k % 9, "scale": scale, "flags": flags,
         "error": error}))
    return str(p)


@pytest.fixture()
def plot(tmp_path):
    cam = tmp_path / "cam.yaml"
    save_camera(Camera([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1]], None, (W, H)), cam)
    photos = [_photo(tmp_path, f"T{k:03d}.jpg", k) for k in range(10)]
    photos.append(_photo(tmp_path, "T100_noexif.jpg", 100, exif=False))
    photos.append(_photo(tmp_path, "T101_noexif.jpg", 101, exif=False))
    photos.append(_photo(tmp_path, "T102 <i>odd & name.jpg", 102, error="no red rope found"))
    return tmp_path, str(cam), photos


def _measure(photos, cam, *extra):
    return CliRunner().invoke(app, ["measure", *photos, "--calib", cam, "--measure-fn", FAKE, *extra],
                              env={"COLUMNS": "250"})


def _rows(page: str) -> list[str]:
    return re.findall(r'<tr id="row-\d+" data-photo="([^"]*)"', page)


def test_report_in_a_browser(plot):
    require_chromium()
    d, cam, photos = plot
    r = _measure(photos, cam, "--csv", str(d / "r.csv"), "--report", str(d / "report.html"),
                 "--plot-area-m2", "400")
    assert r.exit_code == 1, r.output                           # one photo has no rope
    html = (d / "report.html").read_text()
    dom = dump_dom(d / "report.html", d / "chrome")
    data = body_data(dom)
    n = len(photos)
    measured = [json.loads(Path(p + ".truth.json").read_text()) for p in photos]
    dbh = [m["dbh_cm"] for m in measured if not m["error"]]
    assert data["ready"] == "1"
    assert int(data["rows"]) == n and int(data["thumbs"]) == n and int(data["thumbs-loaded"]) == n
    assert int(data["bars"]) == len(dbh_classes(np.array(dbh)))
    assert int(data["map-trees"]) == 10                          # the EXIF-less copies have no position
    import html as h

    assert sorted(h.unescape(p) for p in _rows(dom)) == sorted(photos)   # every photo listed, once
    assert "no red rope found" in dom and "<i>odd" not in html       # errors shown, names escaped
    assert "the scale came from the depth network only" in dom and "Retake: step back" in dom
    assert "Stems per hectare" in dom and f"{len(dbh) * 10000 / 400:.0f}" in dom
    shot = screenshot(d / "report.html", d / "chrome")
    near = lambda c: int(np.sum(np.abs(shot.astype(int) - c).max(axis=2) <= 6))  # noqa: E731
    assert near(BAR) > 2000, "no histogram bars on the screenshot"
    assert near(TREE) > 50, "no trees on the map in the screenshot"


def test_report_sorts_from_the_address(plot):
    require_chromium()
    d, cam, photos = plot
    r = _measure(photos, cam, "--report", str(d / "report.html"))
    assert r.exit_code == 1, r.output
    dom = dump_dom(d / "report.html", d / "chrome", "#sort=dbh_cm-desc")
    assert body_data(dom)["sorted-by"] == "dbh_cm-desc"
    import html as h

    order = [h.unescape(p) for p in _rows(dom)]
    truth = {p: json.loads(Path(p + ".truth.json").read_text()) for p in photos}
    want = sorted((p for p in photos if not truth[p]["error"]), key=lambda p: -truth[p]["dbh_cm"])
    assert order[:len(want)] == want and not truth[order[-1]]["dbh_cm"] is None
    assert truth[order[-1]]["error"]                              # the unmeasured photo sorts last


def test_200_photos_under_20_mb_and_2_s(tmp_path):
    require_chromium()
    cam = tmp_path / "cam.yaml"
    save_camera(Camera([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1]], None, (W, H)), cam)
    # random pixels: the worst case for JPEG, so the thumbnails are larger than a real photo's
    photos = [_photo(tmp_path, f"P{k:03d}.jpg", k) for k in range(200)]
    r = _measure(photos, str(cam), "--report", str(tmp_path / "report.html"))
    assert r.exit_code == 0, r.output
    size_mb = (tmp_path / "report.html").stat().st_size / 1e6
    assert size_mb < 20, f"{size_mb:.1f} MB"
    data = body_data(dump_dom(tmp_path / "report.html", tmp_path / "chrome"))
    assert int(data["rows"]) == 200 and int(data["thumbs-loaded"]) == 200
    assert int(data["load-ms"]) < 2000, data


def test_report_needs_no_network(plot):
    """Self-contained: no URL other than data: and the page's own anchors."""
    d, cam, photos = plot
    assert _measure(photos, cam, "--report", str(d / "report.html")).exit_code == 1
    html = (d / "report.html").read_text()
    refs = re.findall(r'(?:src|href)="([^"]*)"', html)
    assert refs and all(u.startswith(("data:image/jpeg;base64,", "#row-")) for u in refs)
    assert "http://" not in html and "https://" not in html and "@import" not in html


def test_report_refuses_an_input_and_another_output(plot):
    d, cam, photos = plot
    r = _measure(photos[:2], cam, "--report", photos[0])
    assert r.exit_code == 2 and "--report" in r.output
    r = _measure(photos[:2], cam, "--csv", str(d / "x.csv"), "--report", str(d / "x.csv"))
    assert r.exit_code == 2 and "is the --csv file" in r.output
    r = _measure(photos[:2], cam, "--plot-area-m2", "400")
    assert r.exit_code == 2 and "--report" in r.output
    r = _measure(photos[:2], cam, "--report", str(d / "r.html"), "--plot-area-m2", "-3")
    assert r.exit_code == 2 and "> 0" in r.output


def test_resumed_rows_keep_their_thumbnails(plot):
    d, cam, photos = plot
    good = [p for p in photos if "odd" not in p]
    assert _measure(good[:4], cam, "--csv", str(d / "r.csv")).exit_code == 0
    r = _measure(good, cam, "--csv", str(d / "r.csv"), "--resume", "--report", str(d / "report.html"))
    assert r.exit_code == 0, r.output
    html = (d / "report.html").read_text()
    assert len(_rows(html)) == len(good) and html.count('<img class="thumb"') == len(good)
