"""The rope's thickness from its red-ness profile (monodbh.toolkit.rope.profile)."""
import numpy as np

from monodbh.toolkit.rope.profile import profile_thickness, rope_profile_fwhm
from monodbh.toolkit.rope.redness import redness_map


def _band_photo(thickness_px: float, red=(170, 35, 30), bark=(95, 75, 60), W=200, H=120, noise=2.0):
    """A horizontal red band (anti-aliased, rows 60 +- thickness/2) across brown bark."""
    rng = np.random.default_rng(3)
    y = np.arange(H, dtype=np.float64)[:, None]
    cover = np.clip(np.minimum(y - (60 - thickness_px / 2), (60 + thickness_px / 2) - y) + 0.5, 0, 1)
    rgb = np.asarray(bark, np.float64) * (1 - cover[..., None]) + np.asarray(red, np.float64) * cover[..., None]
    rgb = np.broadcast_to(rgb, (H, W, 3)) + rng.normal(0, noise, (H, W, 3))
    return np.clip(rgb, 0, 255).astype(np.uint8)


def test_rope_profile_fwhm_measures_the_band_thickness():
    line = np.array([[20.0, 60.0], [180.0, 60.0]])
    for T in (5.0, 8.0, 12.0):
        fwhm, contrast = rope_profile_fwhm(_band_photo(T), line, T)
        assert abs(fwhm - T) < 0.5, (T, fwhm)
        assert contrast > 0.2
    # a faint rope (a dull red hardly redder than the bark) stands out much less
    _, faint = rope_profile_fwhm(_band_photo(8.0, red=(110, 70, 58)), line, 8.0)
    assert faint < 0.09




def test_profile_thickness_reads_each_column_across_a_tilted_band():
    """The median column FWHM, projected perpendicular to the band (cos of its slope)."""
    for T in (4.0, 7.0):
        F = redness_map(_band_photo(T))
        coef = np.array([0.0, 60.0])                       # y = 60 at every x (window at 0, 0)
        assert abs(profile_thickness(F, np.arange(20, 180), coef, 0, 0, T) - T) < 0.5
    # a band 5 px thick sloping 0.5: each column crosses it over 5 * sqrt(1.25) px
    T, s = 5.0, 0.5
    y, x = np.mgrid[0:160, 0:200].astype(np.float64)
    vert = T * np.hypot(1.0, s)
    F = np.clip(vert / 2 + 0.5 - np.abs(y - (80 + s * (x - 100))), 0, 1).astype(np.float32) * 0.3
    coef = np.array([s, 80 - 100 * s])
    assert abs(profile_thickness(F, np.arange(60, 140), coef, 0, 0, T) - T) < 0.3
    # no peak anywhere: the rough thickness comes back
    F = np.zeros((120, 200), np.float32)
    assert profile_thickness(F, np.arange(20, 180), np.array([0.0, 60.0]), 0, 0, 5.0) == 5.0
