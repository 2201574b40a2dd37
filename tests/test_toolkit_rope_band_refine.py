"""The full-resolution refinement of a chosen band (monodbh.toolkit.rope.band_refine)."""
import numpy as np

from monodbh.toolkit.rope.band_refine import refine_band
from monodbh.toolkit.rope.detection import RopeCandidate


def _photo(T=4.0):
    """A rope-red band ``T`` px thick (rows 120 +- T/2) across a trunk at x 100-200, sloping 0.05."""
    rng = np.random.default_rng(1)
    img = np.clip(rng.normal(0, 2, (240, 320, 3)) + (70, 110, 60), 0, 255)
    img[:, 100:201] = (95, 75, 55)
    y, x = np.mgrid[0:240, 0:320].astype(np.float64)
    yc = 120 + 0.05 * (x - 150)
    cover = np.clip(T / 2 + 0.5 - np.abs(y - yc), 0, 1) * ((x >= 100) & (x <= 200))
    img = img * (1 - cover[..., None]) + np.array([170, 25, 20]) * cover[..., None]
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def _candidate(y_off=0.0):
    xs = np.linspace(104, 196, 24)
    poly = np.stack([xs, 120 + 0.05 * (xs - 150) + y_off], 1).astype(np.float32)
    return RopeCandidate(center_xy=(150.0, 120.0 + y_off), direction=(1.0, 0.0), length_px=93.0, thickness_px=3.0,
                         polyline=poly)


def test_refined_band_follows_the_rope():
    ref = refine_band(_photo(), _candidate(y_off=1.5), None)     # found 1.5 px off on the working copy
    assert abs(ref.center_xy[1] - 120.0) < 0.5 and abs(ref.direction[1] / ref.direction[0] - 0.05) < 0.02
    assert abs(ref.thickness_px - 4.0) < 0.8
    assert ref.mask.shape == (240, 320) and ref.mask[118:123, 110:190].any(0).all()
    assert not ref.mask[:100].any() and not ref.mask[140:].any()
    assert ref.polyline.dtype == np.float32 and ref.polyline[0, 0] <= 106 and ref.polyline[-1, 0] >= 194


def test_a_tree_mask_centres_on_the_trunk():
    mask = np.zeros((240, 320), bool)
    mask[:, 90:171] = True                                       # the trunk as segmented: x 90-170
    ref = refine_band(_photo(), _candidate(), mask)
    assert abs(ref.center_xy[0] - 130.0) < 1e-9



def test_a_centre_line_through_the_band_ends_only_is_straight():
    # a wide strap read with too thin a line filter: band pixels only in the 12 columns at each
    # end, each run tilted; a quadratic through them would bow far out of the strap
    from monodbh.toolkit.rope.band_refine import _fit_centre_line
    H, W = 120, 200
    xs = np.arange(W, dtype=np.float32)
    yy = np.arange(H, dtype=np.float32)[:, None]
    m = np.zeros((H, W), bool)
    R = np.zeros((H, W), np.float32)
    for x in list(range(0, 12)) + list(range(188, 200)):
        y = 60 + (0.6 * x if x < 100 else 0.6 * (199 - x))       # the ends tilt towards each other
        m[int(y) - 2:int(y) + 3, x] = True
        R[int(y) - 2:int(y) + 3, x] = 1.0
    cols = np.flatnonzero(m.any(0))
    coef, _, poly = _fit_centre_line(R, m, cols, xs, yy, 20.0)
    assert len(coef) == 2                                        # a line, not a bowed quadratic
    assert abs(np.polyval(coef, 100.0) - 63.0) < 3.0
    # the same columns spread over the band: the quadratic is kept (a rope's arc)
    cols2 = np.arange(0, 200, 1)
    m2 = np.zeros((H, W), bool)
    for x in cols2:
        y = 60 + 10 * np.sqrt(max(0.0, 1 - ((x - 100) / 100.0) ** 2))
        m2[int(round(y)) - 1:int(round(y)) + 2, x] = True
    coef2, _, _ = _fit_centre_line(m2.astype(np.float32), m2, np.flatnonzero(m2.any(0)), xs, yy, 3.0)
    assert len(coef2) == 3
