"""toolkit.outputs.report: flags and scale in plain words, retake advice, escaping, the histogram's
bars, the tree map's geometry, thumbnails."""
import math
import re
from datetime import datetime, timezone

import numpy as np
import pytest

from monodbh.toolkit.outputs import report as rp
from monodbh.toolkit.outputs.stand import dbh_classes

WHEN = datetime(2026, 10, 14, 9, 0, tzinfo=timezone.utc)


def _row(photo="a.jpg", dbh=30.0, **kw):
    return {"photo": photo, "dbh_cm": dbh, "dbh_sigma_cm": 1.0, "distance_m": 4.0,
            "scale_source": "stem_base", "flags": [], "error": None, **kw}


def test_every_known_flag_and_scale_has_words():
    assert rp.flag_text("stem_base_edge") == "the stem's foot is outside the photo"
    assert rp.flag_text("some_new_flag") == "some new flag"          # unknown: still readable
    assert "foot" in rp.scale_text("stem_base+network") and "network" in rp.scale_text("stem_base+network")
    assert rp.scale_text(None) == ""
    for flag, words in rp.FLAG_TEXT.items():
        assert words and "_" not in words, flag


@pytest.mark.parametrize("row,marker_known,has,lacks", [
    (_row(), False, [], ["Retake"]),                                            # geometric scale
    (_row(scale_source="network"), False, ["step back", "--rope-mm", "--base X,Y"], []),
    (_row(scale_source="network"), True, ["step back", "5 px"], ["--rope-mm"]),
    (_row(scale_source="network", flags=["stem_base_edge"]), False, ["step back"], ["--base"]),
    (_row(scale_source="network", flags=["stem_base_occluded"]), False, ["step back"], ["--base"]),
    (_row(flags=["few_pixels_across_stem"]), False, ["closer"], ["step back"]),
    (_row(flags=["width_disagrees_rope"]), False, ["neighbouring trunk"], []),
    (_row(flags=["stem_base_from_network", "stem_base_ambiguous"]), False, ["--base X,Y"], ["Retake"]),
    (_row(error="a.jpg: no red rope found", dbh=None), False, [], ["Retake"]),
])
def test_retake_advice(row, marker_known, has, lacks):
    got = rp.retake_advice(row, marker_known)
    for h in has:
        assert h in got, got
    for x in lacks:
        assert x not in got, got
    if not has:
        assert got == ""


def test_every_row_is_listed_and_names_are_escaped():
    rows = [_row("<script>alert(1)</script>.jpg"), _row("b&c.jpg", 41.0),
            _row("bad.jpg", None, error='bad.jpg: not a photo "<img>"')]
    page = rp.render_report(rows, generated_at=WHEN)
    assert "<script>alert" not in page and "&lt;script&gt;alert(1)&lt;/script&gt;.jpg" in page
    assert 'data-photo="b&amp;c.jpg"' in page and "not a photo &quot;&lt;img&gt;&quot;" in page
    assert len(re.findall(r'<tr id="row-\d+"', page)) == 3
    assert "2026-10-14 09:00 UTC" in page
    assert not re.search(r'(src|href)="(https?:)?//', page)            # works offline


def test_histogram_has_a_bar_per_class():
    d = [12.0, 14.9, 15.0, 31.0, 33.0, 33.5]
    page = rp.render_report([_row(f"{k}.jpg", v) for k, v in enumerate(d)], generated_at=WHEN)
    bars = re.findall(r'<rect class="bar" data-class="([^"]+)" data-trees="(\d+)"', page)
    want = [(c.dbh_class_cm, str(c.trees)) for c in dbh_classes(np.array(d))]
    assert bars == want and sum(int(t) for _, t in bars) == 6


def test_no_tree_positions_no_map_and_nothing_measured_still_renders():
    page = rp.render_report([_row(), _row("b.jpg", 20.0)], generated_at=WHEN)
    assert 'id="map"' not in page and 'id="histogram"' in page
    empty = rp.render_report([_row("x.jpg", None, error="x.jpg: no red rope found")], generated_at=WHEN)
    assert "no tree measured" in empty and len(re.findall(r'<tr id="row-\d+"', empty)) == 1


def test_map_places_trees_north_up_at_true_scale():
    lat0, lon0 = 46.5, 6.6
    dlat = 20.0 / 111_160.0                             # ~20 m north
    dlon = 30.0 / (111_320.0 * math.cos(math.radians(lat0)))  # ~30 m east
    rows = [_row("a.jpg", tree_lat_deg=lat0, tree_lon_deg=lon0),
            _row("b.jpg", tree_lat_deg=lat0 + dlat, tree_lon_deg=lon0),
            _row("c.jpg", tree_lat_deg=lat0, tree_lon_deg=lon0 + dlon)]
    page = rp.render_report(rows, generated_at=WHEN)
    xy = {p: (float(x), float(y)) for p, x, y in
          re.findall(r'<circle class="tree" data-photo="([^"]+)" cx="([\d.]+)" cy="([\d.]+)"', page)}
    bar = re.search(r'<line class="scalebar" x1="([\d.]+)" x2="([\d.]+)".*?<text[^>]*>([\d.]+) m</text>', page)
    px_per_m = (float(bar.group(2)) - float(bar.group(1))) / float(bar.group(3))
    north = (xy["a.jpg"][1] - xy["b.jpg"][1]) / px_per_m          # SVG y grows downwards
    east = (xy["c.jpg"][0] - xy["a.jpg"][0]) / px_per_m
    assert north == pytest.approx(20.0, rel=0.01) and east == pytest.approx(30.0, rel=0.01)
    assert xy["b.jpg"][0] == pytest.approx(xy["a.jpg"][0], abs=0.2)


def test_thumbnail_is_a_small_jpeg():
    rgb = np.random.default_rng(0).integers(0, 255, (960, 1280, 3), dtype=np.uint8)
    jpg = rp.thumbnail_jpeg(rgb, 320)
    from io import BytesIO

    from PIL import Image

    im = Image.open(BytesIO(jpg))
    assert im.format == "JPEG" and im.size == (320, 240)
    small = rp.thumbnail_jpeg(rgb[:100, :80], 320)
    assert Image.open(BytesIO(small)).size == (80, 100)             # never upscaled
    page = rp.render_report([_row()], [jpg], generated_at=WHEN)
    assert page.count('class="thumb"') == 1 and "data:image/jpeg;base64," in page


def test_thumbnails_must_match_rows():
    with pytest.raises(ValueError, match="2 thumbnails for 1 rows"):
        rp.render_report([_row()], [None, None])
