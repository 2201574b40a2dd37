"""toolkit.outputs.overlay: overlay PNG from MeasureResult.debug."""
import numpy as np
from PIL import Image

from monodbh.toolkit.outputs.overlay import OVERLAY_MAX_SIDE, format_dbh, render_overlay, write_overlay
from monodbh.toolkit.result import MeasureResult


def _result(**debug):
    t = np.linspace(np.pi, 2 * np.pi, 40)
    mask = np.zeros((240, 320), bool)
    mask[:, 50:150] = True
    dbg = dict(rope_polyline=np.array([[50, 150], [100, 155], [150, 150]], float), edges_xy=[[50, 160], [150, 160]],
               slice_px=[[50, 160], [150, 160]], slice_uv=np.c_[0.16 * np.cos(t), 3 + 0.16 * np.sin(t)],
               circle=(0.0, 3.0, 0.16), circles={"ellipse": (0.0, 3.0, 0.17)}, tree_mask=mask)
    dbg.update(debug)
    return MeasureResult(photo="x.jpg", dbh_cm=31.4, dbh_sigma_cm=1.2, distance_m=3.0, scale_source="rope",
                         flags=["short_arc"], rope_xy=[200.0, 305.0], debug=dbg)


def test_overlay_png_size_and_drawing(tmp_path):
    img = np.full((240, 320, 3), 60, np.uint8)
    p = write_overlay(tmp_path / "o" / "t_overlay.png", _result(image=img, image_scale=(0.5, 0.5)))
    with Image.open(p) as im:
        assert im.size == (320, 240) and im.mode == "RGB"
        a = np.asarray(im)
    assert (a != 60).any(axis=2).mean() > 0.05  # text box, inset, lines drawn
    assert not list((tmp_path / "o").glob("*.tmp"))


def test_overlay_reads_photo_and_downscales(tmp_path):
    photo = tmp_path / "big.png"
    Image.fromarray(np.zeros((100, OVERLAY_MAX_SIDE + 200, 3), np.uint8)).save(photo)
    r = _result()
    r.photo = str(photo)
    out = render_overlay(r)
    assert out.shape == (round(100 * OVERLAY_MAX_SIDE / (OVERLAY_MAX_SIDE + 200)), OVERLAY_MAX_SIDE, 3)


def test_overlay_error_and_garbage_debug():
    r = MeasureResult(photo="x.jpg", error="x.jpg: no red rope found",
                      debug={"image": np.zeros((50, 60), np.uint8), "edges_xy": "junk", "circle": [np.nan, 0, 1],
                             "slice_xy": np.zeros((0, 2))})
    out = render_overlay(r)
    assert out.shape == (50, 60, 3) and out[..., 0].max() > 200  # red error text


def test_format_dbh():
    assert format_dbh(31.44, 1.23) == "31.4 ± 1.2 cm"
    assert format_dbh(31.44, None) == "31.4 cm" and format_dbh(None, 1.0) == "-"
    assert format_dbh(31.44, 1.23, unicode=False) == "31.4 +/- 1.2 cm"
