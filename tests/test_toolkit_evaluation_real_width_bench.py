"""evaluation.real_width_bench: where the rope is painted, the truth along the measured line, the
summary, and one painted real-looking photo measured end to end."""
import json

import cv2
import numpy as np
import pytest

from monodbh.toolkit.evaluation import real_width_bench as wb


def test_outline_row_is_a_steady_single_run():
    m = np.zeros((200, 100), bool)
    m[20:180, 30:60] = True
    y, xa, xb = wb.outline_row(m)
    assert (xa, xb) == (30, 59) and 20 < y < 180
    # a fork (two runs) near the preferred rows: the first row clear of it is taken
    m2 = m.copy()
    m2[110:126, 44:47] = False
    assert wb.outline_row(m2) == (67, 30, 59)
    # too narrow everywhere: nowhere to paint
    n = np.zeros((200, 100), bool)
    n[20:180, 30:40] = True
    assert wb.outline_row(n) is None


def test_line_run_follows_the_measured_direction():
    m = np.zeros((200, 200), bool)
    m[:, 80:120] = True                         # a 40 px vertical trunk
    assert wb.line_run(m, (100, 100), (1, 0)) == pytest.approx(40, abs=0.5)
    assert wb.line_run(m, (100, 100), (1, 1)) == pytest.approx(40 * np.sqrt(2), abs=0.6)
    assert wb.line_run(m, (10, 100), (1, 0)) is None


def test_summary_counts_and_errors():
    rows = [dict(err_pct=-2.0, at_painted=True, dbh_cm=20.0), dict(err_pct=8.0, at_painted=True, dbh_cm=20.0),
            dict(err_pct=None, at_painted=False, dbh_cm=30.0), dict(err_pct=None, at_painted=None, dbh_cm=None)]
    s = wb.summarise(rows)
    assert (s["painted"], s["measured"], s["elsewhere"], s["not_measured"]) == (4, 2, 1, 1)
    assert s["median_pct"] == pytest.approx(5.0) and s["within5"] == 0.5 and s["within10"] == 1.0


def test_a_painted_trunk_is_measured_at_its_outline(tmp_path):
    # a bark-textured trunk 60 px wide on a sky-and-grass photo, outlined exactly: the rope is
    # painted across it and the pipeline's width at the rope is compared with the outline's
    rng = np.random.default_rng(3)
    H, W = 480, 360
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:300] = (170, 195, 225)
    rgb[300:] = (70, 110, 50)
    bark = np.clip(rng.normal(85, 12, (H, 60, 1)) + np.array([0, -8, -18]), 0, 255)
    rgb[:, 150:210] = bark.astype(np.uint8)
    folder = tmp_path / "photos"
    folder.mkdir()
    cv2.imwrite(str(folder / "one.jpg"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
    outlines = {"photos": {"one.jpg": {"size": [W, H], "trunks": [
        {"polygon": [[150, 20], [209, 20], [209, 470], [150, 470]], "note": "test"}]}}}
    rows = wb.run(folder, tmp_path / "out", outlines, ratios=(0.12,))
    assert len(rows) == 1 and rows[0]["outline_px"] == 60
    r = rows[0]
    assert r["at_painted"], r
    assert abs(r["err_pct"]) < 5.0, r
    json.dumps(rows)
    tapped, = wb.run(folder, tmp_path / "out_tap", outlines, ratios=(0.12,), tap=True)   # --tap: its middle tapped
    assert tapped["at_painted"] and abs(tapped["err_pct"]) < 5.0, tapped


def test_main_refuses_a_missing_folder(tmp_path, capsys):
    assert wb.main([str(tmp_path / "nope")]) == 2
    assert "not a folder" in capsys.readouterr().err
