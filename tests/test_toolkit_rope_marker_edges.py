"""The marker's thickness edge to edge (toolkit/rope/marker_edges.py) on synthetic crops of known
thickness: flat straps and shaded round ropes, blurred, noisy and JPEG-compressed (tests/marker_crops.py)."""
import numpy as np
import pytest

from marker_crops import marker_crop
from monodbh.toolkit.rope.marker_edges import blurred_box, marker_thickness
from monodbh.toolkit.rope.profile import rope_profile_fwhm


def _crop(width, **kw):
    H = int(6 * width + 48)
    return marker_crop(width, size=(200, H), centre_y=H / 2 + 0.37, **kw)


def test_blurred_box_is_the_convolution_of_a_box_with_a_linear_top():
    t = np.linspace(-8, 8, 33)
    u = np.linspace(-3, 2, 20001)
    du = u[1] - u[0]
    s = 0.7
    num = [np.sum((0.5 + 0.2 * u + 0.1 * u * u) * np.exp(-0.5 * ((x - u) / s) ** 2)) * du / (s * np.sqrt(2 * np.pi))
           for x in t]
    assert np.allclose(blurred_box(t, -3, 2, s, 0.5, 0.2, 0.1), num, atol=1e-4)


@pytest.mark.parametrize("width", [5.2, 12.4, 31.3])
@pytest.mark.parametrize("blur", [0.5, 1.0, 1.5])
def test_a_flat_strap_is_read_to_a_small_fraction_of_a_pixel(width, blur):
    for seed in range(3):
        img, line = _crop(width, kind="strap", blur_px=blur, jpeg_quality=90, seed=seed)
        m = marker_thickness(img, line, 1.15 * width)
        assert m is not None and abs(m.width_px - width) <= 0.25, (width, blur, seed, m)
        assert 0 < m.sigma_px < 0.1 * width and m.n_columns > 100      # (the ruler uses it under 10 %)


@pytest.mark.parametrize("width", [8.7, 12.4, 20.0, 31.3])
@pytest.mark.parametrize("blur", [0.5, 1.0])
def test_a_shaded_rope_is_read_edge_to_edge_whatever_its_shading(width, blur):
    """Lit top, dark underside, a highlight along it: the half-maximum width of the red-ness
    reads the rope too thin (up to most of it on a thick rope); the edges do not."""
    errs, fwhm_errs = [], []
    for seed in range(3):
        img, line = _crop(width, kind="rope", blur_px=blur, jpeg_quality=90, seed=seed)
        m = marker_thickness(img, line, 0.9 * width)
        assert m is not None
        errs.append(m.width_px - width)
        fwhm_errs.append(rope_profile_fwhm(img, line, width)[0] - width)
    assert max(abs(e) for e in errs) <= 0.07 * width, errs
    assert np.mean(np.abs(errs)) < np.mean(np.abs(fwhm_errs))


def test_a_tilted_marker_and_a_rough_starting_thickness():
    img, line = _crop(10.0, kind="strap", tilt_deg=12.0, blur_px=0.8)
    for rough in (7.0, 10.0, 14.0):
        m = marker_thickness(img, line, rough)
        assert m is not None and abs(m.width_px - 10.0) <= 0.25


def test_bad_input_is_refused_and_a_short_band_gives_nothing():
    img, line = _crop(8.0, kind="strap")
    with pytest.raises(ValueError, match="uint8"):
        marker_thickness(img.astype(np.float32), line, 8.0)
    with pytest.raises(ValueError, match="positive"):
        marker_thickness(img, line, 0.0)
    assert marker_thickness(img, np.array([[100.0, 50.0], [102.0, 50.0]]), 8.0) is None
    assert marker_thickness(img, line[:1], 8.0) is None


def test_a_marker_thinner_than_its_blur_is_not_resolved():
    img, line = _crop(3.3, kind="strap", blur_px=1.5)
    m = marker_thickness(img, line, 3.3)
    assert m is not None and not m.resolved
    img, line = _crop(12.4, kind="strap", blur_px=1.0)
    assert marker_thickness(img, line, 12.4).resolved


@pytest.mark.parametrize("width", [5.5, 7.0])
def test_an_unresolved_marker_keeps_the_blur_of_the_whole_band_in_its_stretches(width):
    """Under about four blurs the width and the blur trade off in a fit; the four stretches that
    size the 1-sigma are fitted with the whole band's blur, so a clean unresolved strap is read
    within a pixel and its 1-sigma stays under the ruler's 10 % gate."""
    from monodbh.toolkit.rope.marker_edges import _fit, _profiles
    for seed in range(3):
        img, line = _crop(width, kind="strap", blur_px=1.5, jpeg_quality=90, seed=seed)
        m = marker_thickness(img, line, width)
        assert m is not None and not m.resolved
        assert abs(m.width_px - width) < 1.0 and m.sigma_px < 0.1 * m.width_px, (width, seed, m)
        # with the blur and the shadow given, only the edges are fitted (the blur is returned as
        # given): at the band's own fitted blur (optics and JPEG's half-resolution colour) and
        # shadow the same width
        off, prof = _profiles(img, line, width, 0.7, 0.5)
        f = _fit(off, prof.mean(0), width, blur=m.blur_px, shadow=_fit(off, prof.mean(0), width)[6])
        assert f is not None and f[2] == m.blur_px and not f[5]
        assert abs((f[1] - f[0]) - m.width_px) < 0.05


@pytest.mark.parametrize("kind,width,tol", [("rope", 8.7, 0.10), ("rope", 14.0, 0.04), ("strap", 12.4, 0.02),
                                            ("strap", 25.0, 0.02)])
def test_the_markers_shadow_on_the_bark_is_not_read_as_marker(kind, width, tol):
    """Sunlight casts the marker's shadow on the bark below it: darker bark of the same hue. A box
    alone takes a strap's shadow in (60 % thick) and reads a round rope, whose dark underside
    meets the shadow, about 20 % thin; with the shadow beside the box, in the background's
    colour, the marker's own edges come out (a thin rope's dark underside stays ambiguous)."""
    from monodbh.toolkit.rope import marker_edges as me
    for seed in range(3):
        img, line = _crop(width, kind=kind, blur_px=1.0, jpeg_quality=90, seed=seed, shadow_px=0.6 * width)
        m = marker_thickness(img, line, 0.8 * width)
        assert m is not None and abs(m.width_px - width) <= tol * width, (kind, width, seed, m)
        assert m.sigma_px < 0.1 * m.width_px
        if width >= 12:
            # the fit with no shadow (both its widths held at zero) reads it far off
            off, prof = me._profiles(img, line, 0.8 * width, 0.7, 0.5)
            f = me._fit(off, prof.mean(0), 0.8 * width, shadow=(0.0, 0.0))
            assert abs(f[1] - f[0] - width) > 0.15 * width
