"""The band detector (monodbh.toolkit.rope.band) on synthetic photos and drawn variations of them."""
import cv2
import numpy as np
import pytest

from monodbh.toolkit.rope.band import detect_rope
from monodbh.toolkit.rope.detection import RopeDetection

# Rendered once per module at 640x480 (a few seconds each). Verified by hand:
#   seed 11 / index 2: an orange-red rope on a pale birch-like trunk (tree 1), rope centre ~(447, 349);
#   seed 11 / index 24: no rope, no distractors; tree 1 is a large grey trunk, x 342..414 at row 300.
ROPED = (11, 2)
NO_ROPE = (11, 24)


def _render(seed, index):
    pytest.importorskip("embreex")
    from monodbh.models.synthetic import generate_sample
    s = generate_sample(seed, index, (640, 480))
    return dict(rgb=s["rgb"], rope=s["rope"], instance=s["instance"], meta=s["meta"])


@pytest.fixture(scope="module")
def roped():
    s = _render(*ROPED)
    assert s["meta"]["roped_tree"] == 1
    return s


@pytest.fixture(scope="module")
def no_rope():
    s = _render(*NO_ROPE)
    assert s["meta"]["roped_tree"] is None
    return s


def _jpeg(rgb, q=90):
    """Phone-like JPEG round trip (4:2:0 chroma) after drawing, so drawn lines look photographed."""
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, q])
    assert ok
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)[:, :, ::-1].copy()


def _gt(s):
    """GT rope pixels of the roped tree, and the tolerance max(5, half the trunk width)."""
    tree = s["meta"]["roped_tree"]
    m = s["rope"] & (s["instance"] == tree)
    ys, xs = np.nonzero(m)
    row = s["instance"][int(np.median(ys))] == tree
    cols = np.flatnonzero(row)
    return m, max(5.0, 0.5 * (cols[-1] - cols[0] + 1))


def _dist_to_mask(m, xy):
    ys, xs = np.nonzero(m)
    return float(np.min(np.hypot(xs - xy[0], ys - xy[1])))


def _trunk_cols(s, tree, row):
    cols = np.flatnonzero(s["instance"][row] == tree)
    return int(cols[0]), int(cols[-1])


def _draw_rope(rgb, x0, x1, y, width, color=(150, 20, 28), sag=0.12):
    """Anti-aliased elliptic arc ``width`` px thick (front half of a ring seen from above), x0..x1 at row y.

    Returns the image and the arc's middle point (x, y).
    """
    H, W = rgb.shape[:2]
    cx, a = (x0 + x1) / 2, (x1 - x0) / 2
    b = sag * a
    xs = np.arange(W, dtype=np.float64)
    t = np.clip((xs - cx) / a, -1, 1)
    yc = y + b * np.sqrt(1 - t ** 2)
    yy = np.arange(H, dtype=np.float64)[:, None]
    cover = np.clip(width / 2 + 0.5 - np.abs(yy - yc[None, :]), 0, 1)
    cover[:, (xs < x0) | (xs > x1)] = 0
    out = rgb.astype(np.float64) * (1 - cover[..., None]) + np.array(color, np.float64) * cover[..., None]
    return np.clip(np.round(out), 0, 255).astype(np.uint8), (cx, y + b)


# ----------------------------------------------------------------------------- basics

def test_api_and_input_checks():
    det = RopeDetection(False, "nothing")
    assert not det and det.reason == "nothing"
    with pytest.raises(ValueError):
        detect_rope(np.zeros((10, 10), np.uint8))
    with pytest.raises(ValueError):
        detect_rope(np.zeros((40, 40, 3), np.uint8), tree_mask=np.zeros((20, 20), bool))
    det = detect_rope(np.full((120, 160, 3), 90, np.uint8))
    assert not det and not det.found and det.reason and det.mask is None
    # no rope: the user is told how to retake the photo, on one line
    assert det.reason.startswith("no red rope found") and "2 px" in det.reason and "--pick" in det.reason
    assert "\n" not in det.reason


# ----------------------------------------------------------------------------- synthetic photos

def test_finds_rope_on_synthetic_photo(roped):
    det = detect_rope(roped["rgb"])
    gt, tol = _gt(roped)
    assert det, det.reason
    assert det.found and not det.ambiguous
    assert _dist_to_mask(gt, det.center_xy) <= tol
    assert abs(det.direction[1]) < 0.5 and det.direction[0] > 0         # across the trunk, not along it
    assert det.mask.shape == gt.shape and (det.mask & gt).sum() >= 0.3 * det.mask.sum()
    assert 1.0 <= det.thickness_px <= 8.0
    assert det.polyline.shape[1] == 2 and len(det.polyline) >= 2
    assert det.candidates and det.candidates[0].score == det.score


def test_tree_mask_centres_on_trunk(roped):
    tree_mask = roped["instance"] == 1
    det = detect_rope(roped["rgb"], tree_mask)
    gt, tol = _gt(roped)
    assert det and _dist_to_mask(gt, det.center_xy) <= tol
    l, r = _trunk_cols(roped, 1, int(round(det.center_xy[1])))
    assert abs(det.center_xy[0] - (l + r) / 2) <= 3


def test_no_rope_scene(no_rope):
    det = detect_rope(no_rope["rgb"])
    assert not det and not det.found and not det.ambiguous and det.reason


def test_height_check_hook(roped):
    det = detect_rope(roped["rgb"], height_check=lambda c: False)
    assert not det
    seen = []
    det = detect_rope(roped["rgb"], height_check=lambda c: seen.append(c.center_xy) or True)
    assert det and seen


# ----------------------------------------------------------------------------- drawn variations

def test_distractors_do_not_fire(no_rope):
    img = no_rope["rgb"].copy()
    cv2.circle(img, (200, 300), 28, (170, 25, 20), -1, cv2.LINE_AA)                # red blob (jacket, leaves)
    cv2.rectangle(img, (372, 250), (382, 330), (160, 30, 25), -1, cv2.LINE_AA)       # vertical paint mark
    cv2.ellipse(img, (470, 420), (40, 25), 20, 0, 360, (140, 25, 20), -1, cv2.LINE_AA)  # red bush / jacket
    det = detect_rope(_jpeg(img))
    assert not det, det.center_xy


def test_rope_wins_over_drawn_distractors(roped):
    img = roped["rgb"].copy()
    cv2.circle(img, (150, 330), 25, (170, 25, 20), -1, cv2.LINE_AA)                 # red blob
    cv2.rectangle(img, (260, 250), (268, 320), (160, 30, 25), -1, cv2.LINE_AA)       # vertical paint stripe
    l, r = _trunk_cols(roped, 1, 200)                                                 # orange tape, same trunk, higher
    cv2.rectangle(img, (l, 196), (r, 204), (235, 120, 20), -1, cv2.LINE_AA)
    det = detect_rope(_jpeg(img))
    gt, tol = _gt(roped)
    assert det, det.reason
    assert _dist_to_mask(gt, det.center_xy) <= tol


def test_orange_tape_alone_is_not_a_rope(no_rope):
    l, r = _trunk_cols(no_rope, 1, 300)
    img = no_rope["rgb"].copy()
    cv2.rectangle(img, (l, 296), (r, 305), (235, 125, 20), -1, cv2.LINE_AA)           # wide flat orange band
    assert not detect_rope(_jpeg(img))
    # the same trunk with a rope-red band is a rope
    img, _ = _draw_rope(no_rope["rgb"], l, r, 300, 3)
    assert detect_rope(_jpeg(img))


@pytest.mark.parametrize("width", [1.2, 2.0])
def test_thin_rope(no_rope, width):
    l, r = _trunk_cols(no_rope, 1, 300)
    img, (cx, cy) = _draw_rope(no_rope["rgb"], l, r, 300, width)
    det = detect_rope(_jpeg(img))
    assert det, det.reason
    assert abs(det.center_xy[0] - cx) <= 6 and abs(det.center_xy[1] - cy) <= 3
    # the red-ness profile is widened by JPEG's half-resolution chroma: about +1 px on thin ropes
    assert width - 0.5 <= det.thickness_px <= width + 1.5


def test_partly_hidden_rope(roped):
    gt, tol = _gt(roped)
    ys, xs = np.nonzero(gt)
    x0, x1 = xs.min(), xs.max()
    w = x1 - x0
    img = roped["rgb"].copy()
    # a thin stem in front of the middle of the rope: a vertical grey-brown bar over 30 % of its length
    xa, xb = int(x0 + 0.38 * w), int(x0 + 0.62 * w)
    img[:, xa:xb] = (95, 88, 80)
    det = detect_rope(_jpeg(img))
    assert det, det.reason
    assert abs(det.center_xy[1] - np.median(ys)) <= 4
    assert abs(det.center_xy[0] - (x0 + x1) / 2) <= tol


def test_two_equal_ropes_are_ambiguous_and_pick_selects(roped):
    img = np.ascontiguousarray(np.hstack([roped["rgb"], roped["rgb"]]))      # two identical roped trunks
    W = roped["rgb"].shape[1]
    det = detect_rope(img)
    assert not det and det.ambiguous
    assert "--pick" in det.reason and len(det.candidates) >= 2
    xs = sorted(c.center_xy[0] for c in det.candidates[:2])
    assert xs[0] < W <= xs[1]
    gt, tol = _gt(roped)
    ys, gx = np.nonzero(gt)
    right = detect_rope(img, pick_xy=(W + gx.mean(), ys.mean()))
    assert right and right.center_xy[0] > W and not right.ambiguous
    left = detect_rope(img, pick_xy=(gx.mean(), ys.mean()))
    assert left and left.center_xy[0] < W
    assert _dist_to_mask(gt, left.center_xy) <= tol


REAL_TREES = "/work/shared/data/real_trees"


def test_real_rope_free_photos():
    """Real photos without a rope (red-brown bark, twigs, foliage): no rope reported.

    One of the 24 (03, a dark branch across sunlit foliage) currently scores just above the
    threshold; more than one is a regression.
    """
    import glob
    import os
    photos = sorted(glob.glob(os.path.join(REAL_TREES, "*.jpg")))
    if not photos:
        pytest.skip(f"{REAL_TREES} not available")
    flagged = []
    for p in photos:
        det = detect_rope(cv2.imread(p, cv2.IMREAD_COLOR)[:, :, ::-1].copy())
        if det or det.ambiguous:
            flagged.append(os.path.basename(p))
    assert len(flagged) <= 1, flagged


def test_faint_rope_not_crowded_out_by_red_clutter():
    """A patch of red leaf litter (many short bright dashes) outranks a faint rope by the cheap band
    score; the rope's band must still be scored fully (it was cut from the candidate budget)."""
    rng = np.random.default_rng(3)
    img = np.empty((480, 640, 3), np.uint8)
    img[:] = (120, 124, 118)
    img = np.clip(img + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8)
    img[:, 420:500] = (88, 84, 80)                                                  # trunk
    for _ in range(160):                                                             # red leaf litter
        x, y = rng.integers(40, 300), rng.integers(260, 440)
        a, L = rng.uniform(-0.5, 0.5), rng.uniform(6, 14)
        cv2.line(img, (int(x - L * np.cos(a)), int(y - L * np.sin(a))),
                 (int(x + L * np.cos(a)), int(y + L * np.sin(a))), (175, 30, 25), 2, cv2.LINE_AA)
    img, (cx, cy) = _draw_rope(img, 420, 500, 200, 2.0, color=(112, 70, 68))       # faint, dull red
    img = _jpeg(img)
    det = detect_rope(img, min_score=-50)
    assert any(abs(c.center_xy[0] - cx) <= 15 and abs(c.center_xy[1] - cy) <= 6 for c in det.candidates)
    picked = detect_rope(img, pick_xy=(cx, cy))
    assert picked and abs(picked.center_xy[0] - cx) <= 15 and abs(picked.center_xy[1] - cy) <= 6


def test_weak_candidate_reported_only_with_weak_score():
    """A faint rope below ``min_score`` is returned (``weak=True``) only when ``weak_score`` asks."""
    rng = np.random.default_rng(5)
    img = np.empty((480, 640, 3), np.uint8)
    img[:] = (120, 124, 118)
    img = np.clip(img + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8)
    img[:, 280:360] = (88, 84, 80)
    img, (cx, cy) = _draw_rope(img, 280, 360, 240, 2.0, color=(104, 74, 72))
    img = _jpeg(img)
    strict = detect_rope(img, min_score=50.0)
    assert not strict and not strict.weak
    d = detect_rope(img, min_score=50.0, weak_score=-50.0)
    assert d and d.weak and abs(d.center_xy[0] - cx) <= 15 and abs(d.center_xy[1] - cy) <= 6


def test_overlapping_bands_are_one_rope_not_rivals():
    from monodbh.toolkit.rope.band import _overlapping
    from monodbh.toolkit.rope.detection import RopeCandidate

    a = RopeCandidate(center_xy=(406.0, 687.6), direction=(1.0, 0.03), length_px=89.0, thickness_px=3.2)
    b = RopeCandidate(center_xy=(351.2, 687.0), direction=(1.0, 0.0), length_px=110.0, thickness_px=3.3)
    far = RopeCandidate(center_xy=(682.0, 205.0), direction=(0.98, -0.2), length_px=43.0, thickness_px=1.8)
    side = RopeCandidate(center_xy=(520.0, 688.0), direction=(1.0, 0.0), length_px=60.0, thickness_px=3.0)
    assert _overlapping(a, b) and _overlapping(b, a)
    assert not _overlapping(a, far)
    assert not _overlapping(a, side)        # the next trunk's rope at the same height


# ----------------------------------------------------------------------------- configuration

def _drawn_band(color, width, seed=5):
    """A band ``width`` px thick of ``color`` across an 80 px trunk on grey (no renderer needed)."""
    rng = np.random.default_rng(seed)
    img = np.empty((480, 640, 3), np.uint8)
    img[:] = (120, 124, 118)
    img = np.clip(img + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8)
    img[:, 280:360] = (88, 84, 80)
    img, c = _draw_rope(img, 280, 360, 240, width, color=color)
    return _jpeg(img), c


def test_a_stricter_min_score_in_the_config_refuses_the_rope():
    """``BandConfig.min_score``: a candidate scoring above it is a rope (here about 6)."""
    from dataclasses import replace

    from monodbh.toolkit.rope.config import BandConfig

    img, (cx, cy) = _drawn_band((150, 20, 28), 3.0)
    det = detect_rope(img)
    assert det and abs(det.center_xy[1] - cy) <= 3 and 1.0 < det.score < 7.0
    strict = detect_rope(img, config=replace(BandConfig(), min_score=7.0))
    assert not strict and not strict.ambiguous and "no red rope" in strict.reason
    # the same candidates were scored, only the decision moved
    assert [c.score for c in strict.candidates] == [c.score for c in det.candidates]


def test_a_wider_hue_gate_in_the_config_lets_orange_tape_in():
    """``BandConfig.max_hue``: bands more orange than it are tape (no candidate at all); with the
    gate opened the tape is scored like any band."""
    from dataclasses import replace

    from monodbh.toolkit.rope.config import BandConfig

    img, (cx, cy) = _drawn_band((240, 150, 20), 4.0)
    shut = detect_rope(img, min_score=-np.inf)
    assert not shut and not any(abs(c.center_xy[1] - cy) < 6 for c in shut.candidates)
    opened = detect_rope(img, min_score=-np.inf, config=replace(BandConfig(), max_hue=1.0))
    assert opened and abs(opened.center_xy[1] - cy) <= 3
    assert BandConfig().max_hue < opened.candidates[0].hue < 1.0


def test_detections_and_candidates_are_frozen_and_repeatable():
    """The detector assembles each candidate once: nothing mutates them, and a second run gives
    the same values."""
    import dataclasses

    img, _ = _drawn_band((150, 20, 28), 3.0)
    a, b = detect_rope(img), detect_rope(img)
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.candidates[0].score = 0.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.found = False
    assert a.score == b.score and np.array_equal(a.mask, b.mask)
    for c, d in zip(a.candidates, b.candidates):
        assert c.features == d.features and c.score == d.score and np.array_equal(c.polyline, d.polyline)


def test_a_strap_too_wide_for_three_pyramid_levels_is_found_on_the_fourth(no_rope):
    # the trunk at 1600 px (2.5x): a 36 px strap across it is 4.5 px thick only on the fourth
    # level; its centre line stays in the strap's middle (a straight line where the thin-line
    # filter sees only the strap's ends)
    from dataclasses import replace
    from monodbh.toolkit.rope.config import BandConfig
    big = cv2.resize(no_rope["rgb"], (1600, 1200), interpolation=cv2.INTER_CUBIC)
    l, r = _trunk_cols(no_rope, 1, 300)
    img, (cx, cy) = _draw_rope(big, int(2.5 * l), int(2.5 * r + 2), 750, 36, sag=0.05)
    img = _jpeg(img)
    det = detect_rope(img)
    assert det, det.reason
    assert abs(det.center_xy[0] - cx) <= 4 and abs(det.center_xy[1] - cy) <= 3
    assert not detect_rope(img, config=replace(BandConfig(), pyramid_levels=3))


def test_a_wide_strap_round_a_thin_stem_is_kept_when_the_marker_is_wide(no_rope):
    # a 20 px strap round a 72 px trunk is under 5 times as long as thick: a blob to the band
    # detector's default, a band for the cascade when the user's marker is wider than a rope
    from monodbh.toolkit.rope.select import RopeSource, select_rope
    l, r = _trunk_cols(no_rope, 1, 300)
    img, (cx, cy) = _draw_rope(no_rope["rgb"], l, r, 300, 20, sag=0.05)
    img = _jpeg(img)
    assert not detect_rope(img)
    inst = no_rope["instance"]
    plain = select_rope(img, lambda: inst, cell=2.5)
    assert not plain
    wide = select_rope(img, lambda: inst, cell=2.5, marker_width_mm=40.0)
    assert wide and wide.source is RopeSource.BAND
    assert abs(wide.rope.center_xy[0] - cx) <= 6 and abs(wide.rope.center_xy[1] - cy) <= 3


def test_a_strap_like_band_off_every_trunk_is_refused_for_a_wide_marker(no_rope):
    # the rope finder does not check straps: a wide red band on the ground (red leaves, a cloth)
    # must lie across a segmented trunk to be the declared strap
    from monodbh.toolkit.rope.select import Refusal, select_rope
    inst = no_rope["instance"].copy()
    inst[400:480, 20:140] = 0                       # where the segmenter sees no trunk
    img, _ = _draw_rope(no_rope["rgb"], 40, 110, 440, 16, sag=0.05)
    img = _jpeg(img)
    choice = select_rope(img, lambda: inst, cell=2.5, marker_width_mm=40.0)
    assert not choice and choice.refusal is Refusal.WEAK_OFF_TRUNK
    # the same band across a trunk is the strap
    inst[400:480, 30:120] = 1
    assert select_rope(img, lambda: inst, cell=2.5, marker_width_mm=40.0)
