"""The rope from the rope finder's candidates: acceptance, rivals, a tap, the band it returns."""
import numpy as np

from monodbh.models.runtime.rope_finder import rope_components
from monodbh.toolkit.rope.config import FinderConfig
from monodbh.toolkit.rope.finder import band_shaped, rope_from_finder
from monodbh.toolkit.rope.geometry import distance_to_chord

FINDER_MIN_PEAK = FinderConfig().min_peak
FINDER_PICK_RADIUS_PX = FinderConfig().pick_radius_px


def _map(lines, shape=(200, 300), level=6.0):
    z = np.full(shape, -8.0, np.float32)
    for (r, c0, c1, lv) in lines:
        z[r, c0:c1] = lv if lv is not None else level
    return z


def test_one_confident_band_is_the_rope():
    z = _map([(50, 20, 60, None)])
    det = rope_from_finder(rope_components(z), (400, 600))
    assert det and det.score >= FINDER_MIN_PEAK
    assert abs(det.center_xy[1] - 100.5) < 1 and abs(det.direction[1]) < 1e-6
    assert det.polyline[0, 0] < det.polyline[-1, 0] and det.polyline[-1, 0] - det.polyline[0, 0] > 70
    assert det.mask.shape == (400, 600) and det.mask.sum() >= 70


def test_faint_blob_and_rival_are_refused():
    assert not rope_from_finder(rope_components(_map([(50, 20, 60, 1.5)])), (400, 600))     # not confident
    z = np.full((200, 300), -8.0, np.float32)
    z[40:60, 40:60] = 8.0                                                                    # a blob
    assert not rope_from_finder(rope_components(z), (400, 600))
    assert not band_shaped(rope_components(z)[0])
    two = rope_from_finder(rope_components(_map([(50, 20, 60, None), (150, 200, 235, None)])), (400, 600))
    assert not two and two.ambiguous and "--pick" in two.reason
    # a much weaker second band is no rival
    one = rope_from_finder(rope_components(_map([(50, 20, 80, None), (150, 200, 212, None)])), (400, 600))
    assert one and abs(one.center_xy[1] - 100.5) < 1


def test_a_tap_chooses_among_rivals_and_accepts_fainter_bands():
    comps = rope_components(_map([(50, 20, 60, None), (150, 200, 235, 2.0)]))
    det = rope_from_finder(comps, (400, 600), pick_xy=(430.0, 303.0))
    assert det and abs(det.center_xy[1] - 300.5) < 1
    miss = rope_from_finder(comps, (400, 600), pick_xy=(300.0, 200.0))
    assert not miss and "picked point" in miss.reason
    c = comps[0]
    assert distance_to_chord(c.polyline, c.center_xy) < 1e-6
    assert abs(distance_to_chord(c.polyline, (c.center_xy[0], c.center_xy[1] + FINDER_PICK_RADIUS_PX)) - FINDER_PICK_RADIUS_PX) < 1e-3


def test_a_knotted_rope_keeps_its_band_and_a_blob_stays_refused():
    # the band across the stem, a knot at its front and two ends hanging from it (a "T" piece)
    z = _map([(50, 20, 70, None)])
    z[51:53, 42:47] = 6.0                 # the knot
    z[51:75, 43] = 6.0                    # hanging ends
    z[51:70, 46] = 6.0
    comps = rope_components(z)
    assert len(comps) == 1 and comps[0].trimmed and band_shaped(comps[0])
    det = rope_from_finder(comps, (400, 600))
    assert det and abs(det.center_xy[1] - 100.5) < 2 and abs(det.direction[1]) < 0.1
    assert 90 < det.polyline[-1, 0] - det.polyline[0, 0] < 110
    # a red jacket: a blob with a straight edge is no band, trimmed or not
    b = np.full((200, 300), -8.0, np.float32)
    b[40:62, 40:70] = 8.0
    cb = rope_components(b)
    assert not cb[0].trimmed and not rope_from_finder(cb, (400, 600))
    # a vertical red paint mark is not turned into a band either
    v = np.full((200, 300), -8.0, np.float32)
    v[20:80, 100:102] = 8.0
    assert not rope_from_finder(rope_components(v), (400, 600))


def test_finder_check_keeps_supported_ropes_replaces_or_refuses_the_others():
    from monodbh.toolkit.rope.detection import RopeDetection
    from monodbh.toolkit.rope.finder import finder_check, finder_support
    FINDER_SUPPORT_MIN_PEAK = FinderConfig().support_min_peak

    comps = rope_components(_map([(50, 20, 60, None)]))            # the finder's rope at y 100, x 40..120
    on = RopeDetection(True, "", center_xy=(80.0, 101.0), direction=(1.0, 0.0))
    assert finder_support(comps, on.center_xy) >= FINDER_SUPPORT_MIN_PEAK
    assert finder_check(on, comps, (400, 600)) == ("supported", None)
    tape = RopeDetection(True, "", center_xy=(400.0, 300.0), direction=(1.0, 0.0))
    verdict, alt = finder_check(tape, comps, (400, 600))
    assert verdict == "replaced" and abs(alt.center_xy[1] - 100.5) < 1
    # no finder candidate near the band, and none confident elsewhere: refused
    faint = rope_components(_map([(50, 20, 60, 1.5)]))
    assert finder_check(tape, faint, (400, 600)) == ("unsupported", None)
    # a faint finder candidate through the band still supports it (a thin rope)
    assert finder_check(on, faint, (400, 600))[0] == "supported"


def test_components_near_look_at_one_tile_in_photo_pixels():
    import cv2

    from monodbh.models.runtime.rope_finder import RopeFinder

    finder = RopeFinder()
    rng = np.random.default_rng(0)
    img = np.clip(rng.normal(90, 12, (900, 1200, 3)), 0, 255).astype(np.uint8)
    img[:, 700:780] = (70, 55, 40)                                   # a trunk
    cv2.line(img, (700, 601), (779, 603), (200, 30, 25), 4)          # a red rope across it
    near = finder.components_near(img, (740.0, 602.0))
    whole = finder.components(img)
    T = finder.tile
    for c in near:                                                   # inside the tile around the point
        assert 740 - T / 2 - 2 <= c.center_xy[0] <= 740 + T / 2 + 2 and 602 - T / 2 - 2 <= c.center_xy[1] <= 602 + T / 2 + 2
        assert np.allclose(np.mean(c.polyline, 0), c.center_xy, atol=0.6 * c.length_px + 2)
    # the band the whole-photo map finds at the rope is found by the one tile too, at the same place
    at_rope = [c for c in whole if distance_to_chord(c.polyline, (740.0, 602.0)) < 6]
    assert at_rope and any(distance_to_chord(c.polyline, (740.0, 602.0)) < 6 for c in near)


def test_a_different_config_changes_the_finders_acceptance():
    from dataclasses import replace

    comps = rope_components(_map([(50, 20, 60, None)]))
    assert rope_from_finder(comps, (400, 600))
    assert not rope_from_finder(comps, (400, 600), config=replace(FinderConfig(), min_peak=7.0))
    assert not rope_from_finder(comps, (400, 600), config=replace(FinderConfig(), min_length_px=1000.0))
    # a tap 20 px off the band: outside the default pick radius, inside a wider one
    tap = (80.0, 121.0)
    assert not rope_from_finder(comps, (400, 600), pick_xy=tap)
    assert rope_from_finder(comps, (400, 600), pick_xy=tap, config=replace(FinderConfig(), pick_radius_px=25.0))
