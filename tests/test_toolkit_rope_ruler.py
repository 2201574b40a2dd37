"""The rope as a ruler (toolkit/rope/ruler.py): its thickness read again on the full-resolution photo."""
import cv2
import numpy as np
import pytest

from monodbh.calib import Camera
from monodbh.toolkit.frames import work_frame
from monodbh.toolkit.rope.ruler import rope_at_full_resolution, rope_ruler
from monodbh.toolkit.rope import detect_rope


def _photo(W=3200, H=2400, thick=6.0, seed=0):
    """A bark-brown trunk 400 px wide on a green background with a red band ``thick`` px
    thick across it (a slight sag, anti-aliased), JPEG-compressed."""
    rng = np.random.default_rng(seed)
    img = np.empty((H, W, 3), np.uint8)
    img[:] = (70, 110, 60)
    x0, x1 = W // 2 - 200, W // 2 + 200
    img[:, x0:x1] = (95, 75, 55)
    img = np.clip(img.astype(np.int16) + rng.integers(-12, 12, img.shape), 0, 255).astype(np.uint8)
    sup = 4
    yy, xx = np.mgrid[0:240 * sup, 0:(x1 - x0) * sup] / sup
    xc = (xx - (x1 - x0) / 2) / ((x1 - x0) / 2)
    yc = 120 + 10 * (1 - xc ** 2)
    cover = (np.abs(yy - yc) <= thick / 2).astype(np.float32)
    cover = cover.reshape(240, sup, x1 - x0, sup).mean((1, 3))
    y0 = H // 2 - 120
    roi = img[y0:y0 + 240, x0:x1].astype(np.float32)
    red = np.array([170, 25, 20], np.float32)
    img[y0:y0 + 240, x0:x1] = (roi * (1 - cover[..., None]) + red * cover[..., None]).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", img[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 92])
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)[:, :, ::-1].copy()


@pytest.mark.parametrize("dist", [None, (-0.05, 0.01, 0.0, 0.0, 0.0)])
def test_full_resolution_reads_the_thickness_the_working_image_halves(dist):
    rgb = _photo(thick=6.0)
    H, W = rgb.shape[:2]
    f = 0.8 * W
    cam = Camera([[f, 0, W / 2 - 0.5], [0, f, H / 2 - 0.5], [0, 0, 1]], dist or [0.0] * 5, (W, H))
    frame = work_frame(rgb, cam, 1600)
    assert frame.image.shape[1] == 1600 and frame.scale[0] == pytest.approx(0.5)
    rope = detect_rope(frame.image, None)
    assert rope and rope.thickness_px < 4.5                  # 3 px in the working image
    full = rope_at_full_resolution(rgb, cam, frame, rope)
    assert full is not None and full["scale"] == pytest.approx(0.5)
    assert full["thickness_px"] == pytest.approx(6.0, rel=0.2)
    assert full["contrast"] > 0.09
    ruler = rope_ruler(rgb, cam, frame, rope, is_line=True, diameter_known=True)
    # 6 px, read edge to edge where that agrees with the detector's width (under four blurs the
    # width and the blur trade off in the fit, so it is kept only where the two agree)
    assert ruler.flags == ["rope_read_at_full_resolution", "marker_read_by_edges"] and ruler.edges and full["edges"]
    assert ruler.thickness_native_px == full["thickness_px"] == pytest.approx(6.0, abs=0.3)
    assert ruler.thickness_px == pytest.approx(3.0, abs=0.15)
    assert rope_ruler(rgb, cam, frame, rope, is_line=False, diameter_known=True).thickness_px is None
    assert "rope_read_at_full_resolution" not in rope_ruler(rgb, cam, frame, rope, is_line=True, diameter_known=True,
                                                            full_resolution=False).flags


def test_a_thick_band_is_read_edge_to_edge_at_full_resolution():
    rgb = _photo(thick=14.0)
    H, W = rgb.shape[:2]
    f = 0.8 * W
    cam = Camera([[f, 0, W / 2 - 0.5], [0, f, H / 2 - 0.5], [0, 0, 1]], [0.0] * 5, (W, H))
    frame = work_frame(rgb, cam, 1600)
    rope = detect_rope(frame.image, None)
    full = rope_at_full_resolution(rgb, cam, frame, rope)
    assert full["edges"] and full["thickness_px"] == pytest.approx(14.0, abs=0.25)
    fwhm = rope_at_full_resolution(rgb, cam, frame, rope, edges=False)
    assert not fwhm["edges"] and abs(fwhm["thickness_px"] - 14.0) > abs(full["thickness_px"] - 14.0)
    ruler = rope_ruler(rgb, cam, frame, rope, is_line=True, diameter_known=True)
    assert ruler.edges and ruler.flags == ["rope_read_at_full_resolution", "marker_read_by_edges"]
    assert ruler.thickness_px == pytest.approx(7.0, abs=0.15)


def test_full_resolution_needs_a_larger_photo():
    rgb = _photo(W=1600, H=1200, thick=6.0)
    cam = Camera([[1280, 0, 799.5], [0, 1280, 599.5], [0, 0, 1]], [0.0] * 5, (1600, 1200))
    frame = work_frame(rgb, cam, 1600)
    rope = detect_rope(frame.image, None)
    assert rope and rope_at_full_resolution(rgb, cam, frame, rope) is None


def test_a_strap_wider_than_the_detectors_window_is_read_edge_to_edge():
    """The band detector can read a wide strap as a stripe of it (a third of its width); the edge
    reading, 3x that, is read again in a window sized by itself and kept where the half-maximum
    width there agrees; a 10 px rope with a dark shadow a pixel below it, which the edge fit
    cannot settle (its stretches disagree by 16 %), is still refused."""
    from marker_crops import marker_crop
    from monodbh.toolkit.rope.ruler import _refined_width
    for w in (20.0, 28.0):
        img, pl = marker_crop(w, kind="strap", size=(320, 160), centre_y=78.3, blur_px=1.0)
        for T in (w, 0.6 * w, 0.3 * w):
            assert _refined_width(img, pl, T) == (pytest.approx(w, abs=0.3), True)
    img, pl = marker_crop(10.0, kind="rope", size=(320, 120), centre_y=50.3, blur_px=0.8)
    shaded = img.astype(np.float32)
    shaded[56:68] *= 0.45                                    # the rope's shadow on the bark below it
    shaded = shaded.clip(0, 255).astype(np.uint8)
    assert _refined_width(shaded, pl, 10.0) is None


def test_a_thick_rope_read_as_a_stripe_falls_back_on_its_half_maximum_width(monkeypatch):
    """A thick round rope's shaded half is no longer red to the band detector, which reads a
    stripe of it (a third of its thickness). The edges in a window sized by the mean profile's
    half-maximum width read it, clean or with its shadow on the bark below it (fitted beside it);
    where no edge reading holds, that half-maximum width (over ``fwhm_ratio``) is the thickness,
    not the stripe (12 MP photos taken from 2-6 m: a 19.5 px rope read 6.8 px before, distance
    +104 %)."""
    from marker_crops import marker_crop
    from monodbh.toolkit.geometry.config import RopeRulerConfig
    from monodbh.toolkit.rope import marker_edges
    from monodbh.toolkit.rope.ruler import _refined_width
    ratio = RopeRulerConfig().fwhm_ratio
    for w in (16.0, 20.0):
        img, pl = marker_crop(w, kind="rope", size=(320, 160), centre_y=70.3, blur_px=1.0)
        assert _refined_width(img, pl, 0.35 * w) == (pytest.approx(w, abs=0.3), True)
        shaded = img.astype(np.float32)
        y0 = int(70.3 + w / 2)
        shaded[y0:y0 + int(0.6 * w)] *= 0.45                   # the rope's shadow below it
        shaded = shaded.clip(0, 255).astype(np.uint8)
        assert _refined_width(shaded, pl, 0.35 * w) == (pytest.approx(w, abs=0.3), True)
        with monkeypatch.context() as m:
            m.setattr(marker_edges, "marker_thickness", lambda *a, **k: None)     # no edge reading
            width, by_edges = _refined_width(shaded, pl, 0.35 * w)
        assert not by_edges and abs(width / ratio - w) < 0.06 * w


def test_a_finder_band_is_read_as_a_wide_marker():
    """The rope finder's band has no thickness of its own (its rough one here a third of the
    truth): with the marker's width known it is read as a wide marker, edge to edge on the
    full-resolution photo; unknown width, no finder band or no edge reading: no ruler."""
    from types import SimpleNamespace
    from monodbh.toolkit.rope.ruler import wide_marker_width
    rgb = _photo(thick=24.0, seed=3)
    H, W = rgb.shape[:2]
    f = 0.8 * W
    cam = Camera([[f, 0, W / 2 - 0.5], [0, f, H / 2 - 0.5], [0, 0, 1]], [0.0] * 5, (W, H))
    frame = work_frame(rgb, cam, 1600)
    band = detect_rope(frame.image, None)
    assert band
    finder = SimpleNamespace(polyline=band.polyline, center_xy=band.center_xy, thickness_px=4.0)
    ruler = rope_ruler(rgb, cam, frame, finder, is_line=False, diameter_known=True, finder_band=True)
    assert ruler.flags == ["rope_read_at_full_resolution", "marker_read_by_edges"] and ruler.edges
    assert ruler.thickness_native_px == pytest.approx(24.0, abs=0.5)
    assert ruler.thickness_px == pytest.approx(12.0, abs=0.25) and ruler.contrast > 0.09
    assert rope_ruler(rgb, cam, frame, finder, is_line=False, diameter_known=False, finder_band=True).thickness_px is None
    assert rope_ruler(rgb, cam, frame, finder, is_line=False, diameter_known=True).thickness_px is None
    assert rope_ruler(rgb, cam, frame, finder, is_line=False, diameter_known=True, finder_band=True,
                      edges=False).thickness_px is None
    # on the working image alone
    small = rope_ruler(rgb, cam, frame, finder, is_line=False, diameter_known=True, finder_band=True,
                       full_resolution=False)
    assert small.flags == ["marker_read_by_edges"] and small.thickness_px == pytest.approx(12.0, abs=0.4)
    w, by_edges = wide_marker_width(frame.image, band.polyline, 4.0)
    assert by_edges and w == pytest.approx(12.0, abs=0.4)
    # a band 12 px thick at one end and 48 px at the other: its stretches disagree, so the edges
    # do not hold; the mean profile's half-maximum width stands in, only when asked
    rng = np.random.default_rng(0)
    img = np.zeros((200, 320, 3), np.float32)
    img[:] = (112, 96, 80)
    yy, xx = np.mgrid[0:200, 0:320]
    inside = (np.abs(yy - 100.0) <= 6 + 18 * xx / 320).astype(np.float32)[..., None]
    img = img * (1 - inside) + np.array([175, 28, 22], np.float32) * inside
    img = np.clip(cv2.GaussianBlur(img, (0, 0), 1.0) + rng.normal(0, 3, img.shape), 0, 255).astype(np.uint8)
    line = np.array([[20.0, 100.0], [300.0, 100.0]])
    assert wide_marker_width(img, line, 6.0) is None
    w, by_edges = wide_marker_width(img, line, 6.0, fwhm_fallback=True)
    assert not by_edges and 27.0 < w < 33.0                  # 30 px in the middle


def test_a_piece_of_the_band_found_at_full_resolution_is_the_same_rope():
    # an interrupted rope is found at full resolution in pieces: one off the working band's
    # middle but on its line is the same rope; a band beside it is not
    from monodbh.toolkit.rope.ruler import _on_band
    xs = np.linspace(100, 500, 41)
    P = np.stack([xs, 200 + 0.05 * (xs - 300)], 1)              # the working band, 8 px thick
    piece = np.stack([np.linspace(380, 480, 11), 200 + 0.05 * (np.linspace(380, 480, 11) - 300) + 1.5], 1)
    assert _on_band(piece, P, 8.0)
    beside = piece + (0, 30)                                    # a red line 30 px below
    assert not _on_band(beside, P, 8.0)
    outside = piece + (500, 0)                                  # beyond the band's columns
    assert not _on_band(outside, P, 8.0)
