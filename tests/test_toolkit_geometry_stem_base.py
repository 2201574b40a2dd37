"""The stem base: its states and the visible-stem bound (toolkit.geometry.stem_base)."""
from types import SimpleNamespace

import numpy as np
import pytest

from geometry_scenes import level_scene


def test_stem_hidden_by_a_bush_caps_a_too_far_network_scale():
    """The base is at or below where a bush hides the stem: a network distance beyond the
    metrology through that point is capped to it (5 m true; 8.5 m network; bound 5 x 1.3 / 0.9)."""
    from monodbh.toolkit.geometry import GeometryConfig, Perception, StemBaseConfig, measure_from_perception
    for bush in (True, False):
        rgb, tree, ground, depth, cam = level_scene(bush)
        p = Perception(rgb=rgb, camera=cam, rope_xy=np.array([240.0, 320.0]), rope_dir=np.array([1.0, 0.0]),
                       rope_half_px=2.0, tree_mask=tree, ground_mask=ground, depth=depth,
                       source="network", use_vanishing=False,
                       sigma_network={"network": 0.37, "stem_base": 0.05})
        r = measure_from_perception(p)
        assert r.error is None, r.error
        if bush:
            assert "scale_capped_by_visible_stem" in r.flags
            assert r.scale_source.startswith("visible_stem+network")
            assert 6.9 < r.distance_m < 7.6                       # not 8.8: capped near 7.3
        else:
            # the edges are followed down to the ground: that end bounds the distance (the foot
            # is there or lower) and caps the too-far network scale near the truth
            assert "stem_base_tracked" in r.flags and "scale_capped_by_visible_stem" in r.flags
            assert r.scale_source.startswith("visible_stem+network"), r.scale_source
            assert r.distance_m == pytest.approx(5.15, rel=0.03)    # to the axis: 5 m + radius
            # as a base (the option): it sets the scale itself
            r = measure_from_perception(p, config=GeometryConfig(stem_base=StemBaseConfig(tracked_base_sets_scale=True)))
            assert r.scale_source.startswith("stem_base"), r.scale_source
            assert r.distance_m == pytest.approx(5.15, rel=0.03)
            assert "scale_capped_by_visible_stem" not in r.flags
    # a distance calibration (error model) applies to network-led scales only, before the cap
    rgb, tree, ground, depth, cam = level_scene(False)
    kw = dict(rgb=rgb, camera=cam, rope_xy=np.array([240.0, 320.0]), rope_dir=np.array([1.0, 0.0]),
              rope_half_px=2.0, tree_mask=tree, ground_mask=np.zeros_like(ground), depth=depth,
              source="network", use_vanishing=False)
    r0 = measure_from_perception(Perception(**kw))
    r1 = measure_from_perception(Perception(**kw, distance_calibration={"a": 0.0, "b": 0.7}))
    assert "distance_calibrated" in r1.flags and r1.scale_source == "network"
    lam0 = r0.debug["lam_combined"]                     # 8.8 m: capped to 5.2 without calibration
    assert r1.debug["lam_uncalibrated"] == pytest.approx(lam0)
    lam1 = np.exp(0.7 * np.log(lam0))                   # 4.6 m: below the bound, not capped
    assert np.linalg.norm(r1.debug["axis_point"]) == pytest.approx(lam1, rel=1e-6)
    assert r1.dbh_cm / r0.dbh_cm == pytest.approx(lam1 / np.linalg.norm(r0.debug["axis_point"]), rel=2e-3)
    # the calibrated distances' own measured spread replaces the raw network's sigma
    r2 = measure_from_perception(Perception(**kw, distance_calibration={"a": 0.0, "b": 0.7, "sigma": 0.2}))
    assert r2.dbh_cm == pytest.approx(r1.dbh_cm)
    assert r2.dbh_sigma_cm / r2.dbh_cm < r1.dbh_sigma_cm / r1.dbh_cm
    assert r2.dbh_sigma_cm / r2.dbh_cm == pytest.approx(0.2, abs=0.05)


def _level_stem():
    """The level scene's camera and the stem's edges and axis at the rope (row 320, 5 m away)."""
    from monodbh.toolkit.geometry import TrunkEdges
    from monodbh.toolkit.geometry.up import stem_axis
    rgb, tree, ground, depth, cam = level_scene(False)
    half = 0.5 * 500.0 * 0.3 / 5.0
    edges = TrunkEdges(left_xy=np.array([240.0 - half, 320.0]), right_xy=np.array([240.0 + half, 320.0]),
                       width_px=2 * half, along=np.array([0.0, 1.0]), across=np.array([1.0, 0.0]))
    return rgb, tree, ground, cam, edges, stem_axis(cam, edges, np.array([0.0, -1.0, 0.0]))


def test_base_metrology_gives_the_axis_distance_at_the_rope():
    from monodbh.toolkit.geometry.stem_base import StemBase, base_metrology, visible_stem_bound
    *_, cam, edges, axis = _level_stem()
    lt, lb = base_metrology(cam, axis, (240.0, 450.0))          # the front contact, 1.5 m below the camera
    assert lt == pytest.approx(np.hypot(5.15, 0.2), rel=0.02) and lb > lt
    # the lowest tracked point where a bush hides the stem (0.4 m up) bounds the distance from above
    bound = visible_stem_bound(cam, axis, StemBase(None, "occluded", {"end_xy": np.array([240.0, 410.0])}))
    assert bound[1] == "occluded" and bound[0] > lt
    assert visible_stem_bound(cam, axis, StemBase(np.array([240.0, 450.0]), "ground", {"end_xy": (240.0, 450.0)})) is None
    assert visible_stem_bound(cam, axis, StemBase(None, "unconfirmed")) is None


def test_stem_base_states():
    from monodbh.toolkit.geometry import Perception, StemBaseConfig
    from monodbh.toolkit.geometry.stem_base import find_stem_base
    from monodbh.toolkit.result import MeasureResult
    rgb, tree, ground, cam, edges, axis = _level_stem()
    gray = rgb.astype(np.float32).mean(2)
    calls = []

    def finder(rgb_, top_xy, along, width_px):
        calls.append(width_px)
        return SimpleNamespace(xy=(240.0, 449.0), p_base=0.4)

    def perc(**kw):
        return Perception(rgb=rgb, camera=cam, rope_xy=np.array([240.0, 320.0]), rope_dir=np.array([1.0, 0.0]),
                          rope_half_px=2.0, tree_mask=tree, ground_mask=ground, **kw)

    def find(p, flags, config=None):
        return find_stem_base(p, gray, edges, axis, {}, MeasureResult(photo=""), flags, config)

    flags = []
    b = find(perc(base_xy=np.array([241.0, 450.0]), base_finder=finder), flags)
    assert b.status == "user" and flags == ["stem_base_from_user"] and not calls
    flags = []
    b = find(perc(base_finder=finder), flags)                     # p 0.4 < 0.5: a weak network base
    assert b.status == "network_weak" and np.allclose(b.xy, [240.0, 449.0]) and flags == ["stem_base_from_network"]
    assert find(perc(base_finder=finder), [], StemBaseConfig(p_strong=0.3)).status == "network"
    # no segmented stem (the tree mask is the rope band's) or edges that disagree with the rope:
    # the network still reads the strip below the rope, but the edge tracker does not follow
    # edges it cannot confirm
    n = len(calls)
    b = find(perc(base_finder=finder, extra={"tree_mask_from_rope": True}), [])
    assert b.status == "network_weak" and np.allclose(b.xy, [240.0, 449.0]) and len(calls) > n
    n = len(calls)
    b = find(perc(base_finder=finder), ["width_disagrees_rope"])
    assert b.status == "network_weak" and len(calls) > n
    assert find(perc(extra={"tree_mask_from_rope": True}), []).status == "unconfirmed"
    assert find(perc(), ["width_disagrees_rope"]).status == "unconfirmed"
    from monodbh.models.runtime.stem_base import BaseEstimate
    nothing = lambda *a: BaseEstimate(None, 0.1, 0.0, "none")
    assert find(perc(base_finder=nothing), ["width_disagrees_rope"]).status == "unconfirmed"
    # no network: the edge tracker follows the stem down to the ground; that end is a bound,
    # not a base, unless the option makes it one
    b = find(perc(), [])
    assert b.status == "tracked" and b.xy is None and abs(b.track_info["end_xy"][1] - 449.5) < 2.0
    b = find(perc(), [], StemBaseConfig(tracked_base_sets_scale=True))
    assert b.status == "ground" and b.track_info is not None and abs(b.xy[1] - 449.5) < 2.0


def test_a_network_base_above_the_segmented_stem_is_a_bush_in_front_not_the_foot():
    """The stem is segmented down to row 449 (0.0 m); a network "base" at row 390 (0.5 m up,
    the top of a bush in front) would put the stem 1.3 / 0.8 farther: it only bounds the
    distance, through the lowest segmented point; a base near the mask's end is kept."""
    from monodbh.toolkit.geometry import Perception, StemBaseConfig
    from monodbh.toolkit.geometry.stem_base import find_stem_base, visible_stem_bound
    from monodbh.toolkit.result import MeasureResult
    rgb, tree, ground, cam, edges, axis = _level_stem()
    gray = rgb.astype(np.float32).mean(2)

    def find(base_row, mask=tree, config=None, extra=None):
        finder = lambda *a: SimpleNamespace(xy=(240.0, base_row), p_base=0.95)
        p = Perception(rgb=rgb, camera=cam, rope_xy=np.array([240.0, 320.0]), rope_dir=np.array([1.0, 0.0]),
                       rope_half_px=2.0, tree_mask=mask, ground_mask=ground, base_finder=finder,
                       extra=extra or {})
        flags = []
        return find_stem_base(p, gray, edges, axis, {}, MeasureResult(photo=""), flags, config), flags

    b, flags = find(390.0)
    assert b.xy is None and b.status == "occluded" and flags == ["stem_base_above_visible_stem"]
    assert abs(b.track_info["end_xy"][1] - 449.0) < 1.5
    bound, _ = visible_stem_bound(cam, axis, b)
    assert bound == pytest.approx(np.hypot(5.15, 0.2), rel=0.03)      # the true distance: the stem ends at its foot
    # leaves in front (gaps under half a stem width) do not end the segmented stem
    holes = tree.copy()
    holes[400:404] = False
    assert find(390.0, holes)[0].status == "occluded"
    # a gap longer than half a stem width ends it: the mask below is not this stem's run
    cut = tree.copy()
    cut[392:420] = False
    assert find(390.0, cut)[0].status == "network"
    # the foot itself, or a base within the allowed overrun, stays a base
    assert find(449.0)[0].status == "network"
    assert find(430.0)[0].status == "network"                            # 0.15 of the span above the mask's end
    assert find(430.0, config=StemBaseConfig(mask_overrun_max=0.1))[0].status == "occluded"
    # a tree mask drawn from the rope band (the segmenter missed the stem) runs past any base:
    # it is not a segmented stem, so it refuses none
    assert find(390.0, extra={"tree_mask_from_rope": True})[0].status == "network"


def test_a_base_that_moves_lower_in_a_strip_cut_a_little_wider_is_read_between_the_two():
    """The network puts the base at row 400 (the top of grass hiding the foot) in the strip cut
    as the edges say, and at row 449 (the foot) in the strip cut 1.2x wider: the base is
    ambiguous and flagged; the scale is the geometric mean of the two bases' distances, its
    sigma widened by half their log ratio. A base that stays put under every strip is kept as
    it is; the check can be switched off."""
    from monodbh.toolkit.geometry import Perception, StemBaseConfig
    from monodbh.toolkit.geometry.scale import candidate_stem_base
    from monodbh.toolkit.geometry.sigma import SigmaTables
    from monodbh.toolkit.geometry.stem_base import base_metrology, find_stem_base
    from monodbh.toolkit.result import MeasureResult
    rgb, tree, ground, cam, edges, axis = _level_stem()
    gray = rgb.astype(np.float32).mean(2)
    w0 = float(edges.width_px)
    tree = tree.copy()
    tree[402:] = False                  # the segmented stem ends where the grass begins

    def find(finder, config=None):
        p = Perception(rgb=rgb, camera=cam, rope_xy=np.array([240.0, 320.0]), rope_dir=np.array([1.0, 0.0]),
                       rope_half_px=2.0, tree_mask=tree, ground_mask=ground, base_finder=finder)
        flags, res = [], MeasureResult(photo="")
        return find_stem_base(p, gray, edges, axis, {}, res, flags, config), flags, res

    def moving_with(p):
        return lambda rgb_, top, along, w: SimpleNamespace(xy=(240.0, 449.0 if w > 1.1 * w0 else 400.0), p_base=p)
    moving = moving_with(0.92)
    b, flags, res = find(moving)
    assert b.status == "network_ambiguous" and np.allclose(b.xy, [240.0, 400.0])
    assert np.allclose(b.track_info["lower_xy"], [240.0, 449.0])
    assert flags == ["stem_base_from_network", "stem_base_ambiguous"]
    assert res.debug["base_lower_nearby"] == pytest.approx(49.0 / 80.0, rel=0.05)   # rows 320 -> 400 -> 449
    tables = SigmaTables(model={}, network={"stem_base_weak": 0.1}, net=True)
    src, (lam, sigma) = candidate_stem_base(cam, axis, b, {}, tables, [])
    l_top, _ = base_metrology(cam, axis, (240.0, 400.0))
    l_foot, _ = base_metrology(cam, axis, (240.0, 449.0))
    assert l_top > 1.3 * l_foot                       # the top of the grass reads the stem far too far
    assert src == "stem_base_weak" and lam == pytest.approx(np.sqrt(l_top * l_foot))
    assert sigma == pytest.approx(np.hypot(0.1, 0.5 * np.log(l_top / l_foot)))
    # the network's base as it is where the check is off, or where the lower base is within the tolerance
    assert find(moving, StemBaseConfig(ambiguity_strips=()))[0].status == "network"
    assert find(moving, StemBaseConfig(ambiguity_max_lower=0.7))[0].status == "network"
    # a base the network is surer of than ambiguity_p_max is not cut again
    b, _, res = find(moving_with(0.97))
    assert b.status == "network" and res.debug["base_lower_nearby"] == 0.0
    steady = lambda *a: SimpleNamespace(xy=(240.0, 449.0), p_base=0.95)
    b, flags, res = find(steady)
    assert b.status == "network" and flags == ["stem_base_from_network"] and res.debug["base_lower_nearby"] == 0.0
    # a base the second stem-base network found says so
    second = lambda *a: SimpleNamespace(xy=(240.0, 449.0), p_base=0.95, network="stem_base_net")
    b, flags, _ = find(second)
    assert b.status == "network" and flags == ["stem_base_from_network", "stem_base_second_network"]
