"""The scale candidates and their combination (toolkit.geometry.scale)."""
from types import SimpleNamespace

import numpy as np
import pytest

from monodbh.toolkit.geometry import RopeRulerConfig, ScaleConfig
from monodbh.toolkit.geometry.scale import (calibrate_distance, candidate_depth, candidate_rope_diameter,
                                            capped_by_visible_stem, combine_candidates,
                                            rope_ruler_sigma)
from monodbh.toolkit.geometry.sigma import sigma_tables


def _tables(net=True):
    return sigma_tables(SimpleNamespace(sigma_network=None, source="network" if net else "ground_truth"))


def test_agreeing_sources_are_combined_by_inverse_variance_and_a_disagreeing_one_is_flagged():
    cands = {"stem_base": (5.0, 0.04), "ground_plane": (5.2, 0.05), "camera_height": (8.0, 0.10)}
    flags = []
    ch = combine_candidates(cands, rank={}, correlated=False, flags=flags)
    assert ch.leader == "stem_base"                      # the least sigma leads without a rank
    w1, w2 = 1 / 0.04 ** 2, 1 / 0.05 ** 2
    assert ch.lam == pytest.approx((w1 * 5.0 + w2 * 5.2) / (w1 + w2), rel=1e-12)
    assert ch.sig_rel == pytest.approx(1 / np.sqrt(w1 + w2), rel=1e-12)
    assert ch.used == ["stem_base", "ground_plane"] and ch.source == "stem_base+ground_plane"
    assert flags == ["scale_disagree_camera_height"]
    # correlated sources (network perception): agreeing does not shrink the sigma
    ch = combine_candidates(cands, rank={}, correlated=True, flags=[])
    assert ch.sig_rel == 0.04


def test_a_wide_marker_read_to_a_few_per_cent_leads_over_a_stem_base():
    """The error model's typical error of the marker (0.10) is that of thin ropes; a strap read edge
    to edge across 20 px has a sigma of 0.03, less than the stem base's typical error: it leads,
    and a stem base 28 % off is flagged instead of setting the scale. A thin rope (sigma 0.09)
    still follows the stem base."""
    rank = {"stem_base": 0.0375, "rope_diameter": 0.100}
    flags = []
    ch = combine_candidates({"stem_base": (6.4, 0.054), "rope_diameter": (5.0, 0.033)}, rank=rank,
                            correlated=True, flags=flags)
    assert ch.leader == "rope_diameter" and ch.lam == 5.0 and flags == ["scale_disagree_stem_base"]
    ch = combine_candidates({"stem_base": (6.4, 0.054), "rope_diameter": (5.0, 0.09)}, rank=rank,
                            correlated=True, flags=[])
    assert ch.leader == "stem_base"


def test_a_stricter_agreement_threshold_keeps_the_sources_apart():
    cands = {"stem_base": (5.0, 0.04), "ground_plane": (5.2, 0.05)}
    flags = []
    # 4 % apart: within 2.5 combined sigmas (16 %) by default, not within 0.5 (3.2 %)
    ch = combine_candidates(cands, rank={}, correlated=False, flags=flags, config=ScaleConfig(agree_sigmas=0.5))
    assert ch.lam == 5.0 and ch.source == "stem_base" and flags == ["scale_disagree_ground_plane"]


def test_the_rank_picks_the_leader_and_the_network_is_averaged_in_only_when_it_leads():
    cands = {"ground_plane": (4.1, 0.47), "network": (4.0, 0.37)}
    # ground_plane is ranked by its network error-model key
    ch = combine_candidates(cands, rank={"network": 0.3, "ground_plane_network": 0.2}, correlated=True, flags=[])
    assert ch.leader == "ground_plane" and ch.source == "ground_plane" and ch.lam == 4.1
    ch = combine_candidates(cands, rank={"network": 0.1, "ground_plane_network": 0.2}, correlated=True, flags=[])
    assert ch.leader == "network" and ch.source == "network+ground_plane"


def test_distance_calibration_shrinks_towards_the_typical_distance():
    lam, sig = calibrate_distance(9.0, 0.37, {"a": 0.34, "b": 0.71})
    assert lam == pytest.approx(np.exp(0.34 + 0.71 * np.log(9.0))) and sig == 0.37
    assert calibrate_distance(9.0, 0.37, {"a": 0.34, "b": 0.71, "sigma": 0.25})[1] == 0.25


def test_visible_stem_cap_follows_its_configuration():
    bound = (5.0, "occluded")
    assert capped_by_visible_stem(5.2, "network", bound)                     # 4 % beyond, slack 3 %
    assert not capped_by_visible_stem(5.1, "network", bound)
    assert not capped_by_visible_stem(5.2, "network", bound, ScaleConfig(bound_slack=0.05))
    assert not capped_by_visible_stem(5.2, "stem_base", bound)                # a precise source is not capped
    assert not capped_by_visible_stem(5.2, "network", (5.0, "edge"))
    assert capped_by_visible_stem(5.2, "network", (5.0, "edge"), ScaleConfig(bound_statuses=("occluded", "edge")))
    assert not capped_by_visible_stem(5.2, "network", None)


def test_a_marker_read_to_a_few_per_cent_is_flagged_not_capped_by_the_visible_stem():
    """A stem followed down into its own shadow ends below its foot, so its bound can be too near;
    a marker read edge to edge (sigma under ``bound_min_sigma``) stands and the photo is flagged,
    while a stripe-read one (a wider sigma) is still capped."""
    from types import SimpleNamespace
    from monodbh.toolkit.geometry.scale import beyond_visible_stem, choose_scale
    bound = (5.0, "occluded")
    assert beyond_visible_stem(5.2, "rope_diameter", bound)
    assert not capped_by_visible_stem(5.2, "rope_diameter", bound, sig_rel=0.04)
    assert capped_by_visible_stem(5.2, "rope_diameter", bound, sig_rel=0.14)
    assert capped_by_visible_stem(5.2, "rope_diameter", bound, ScaleConfig(bound_min_sigma=0.03), sig_rel=0.04)
    perc = SimpleNamespace(source="network", rank_network={}, distance_calibration=None)
    for sig, lam, flag in ((0.04, 7.0, "scale_disagree_visible_stem"), (0.14, 5.0, "scale_capped_by_visible_stem")):
        res, flags = SimpleNamespace(scale_source=None, debug={}), []
        ch = choose_scale(perc, {"rope_diameter": (7.0, sig)}, bound, res, flags)
        assert ch.lam == lam and flag in flags and len([f for f in flags if "visible_stem" in f]) == 1


def _rope(thickness_px, native_px=None, contrast=0.2, diameter_m=0.01, edges=False):
    from monodbh.calib import Camera
    cam = Camera(np.array([[1000.0, 0, 320], [0, 1000.0, 240], [0, 0, 1]]), None, (640, 480))
    return SimpleNamespace(rope_diameter_m=diameter_m, rope_thickness_px=thickness_px,
                           rope_thickness_native_px=native_px, rope_contrast=contrast, rope_thickness_edges=edges,
                           rope_dir=np.array([1.0, 0.0]), rope_xy=np.array([320.0, 240.0]), camera=cam)


def test_the_rope_as_a_ruler_and_its_gates():
    axis = SimpleNamespace(sin_half=0.0)
    T = 8.0 * RopeRulerConfig().fwhm_ratio              # a 10 mm rope whose tube is 8 px: 1.25 m away
    flags = []
    name, (lam, sig) = candidate_rope_diameter(_rope(T), axis, flags)
    assert name == "rope_diameter" and flags == []
    assert lam == pytest.approx(0.01 * 1000 / 8.0 + 0.005, rel=1e-4) and sig == pytest.approx(np.hypot(0.08, 0.8 / T))
    # its sigma follows the pixels it was read in: a thicker marker, read edge to edge, is a finer ruler
    assert rope_ruler_sigma(20.0, True) == pytest.approx(np.hypot(0.025, 0.45 / 20))
    assert rope_ruler_sigma(20.0, True) < rope_ruler_sigma(8.0, True) < rope_ruler_sigma(8.0, False)
    # read edge to edge, the thickness is the tube's own (no half-maximum correction)
    _, (lam_e, _) = candidate_rope_diameter(_rope(8.0, edges=True), axis, [])
    assert lam_e == pytest.approx(lam, rel=1e-4)
    # too thin where it was measured (the native pixels decide), too faint
    assert candidate_rope_diameter(_rope(T, native_px=4.0), axis, flags) is None
    assert candidate_rope_diameter(_rope(T, contrast=0.05), axis, flags) is None
    assert flags == ["rope_too_thin_for_scale", "rope_too_faint_for_scale"]
    # a looser configuration trusts the 4 px rope
    assert candidate_rope_diameter(_rope(T, native_px=4.0), axis, [], RopeRulerConfig(min_px=3.0))
    assert candidate_rope_diameter(_rope(T, diameter_m=None), axis, []) is None
    # found (by the rope finder, through the stem's profile) but not seen as a line: no thickness
    flags = []
    assert candidate_rope_diameter(_rope(None), axis, flags) is None
    assert flags == ["marker_not_read_for_scale"]


def test_the_depth_maps_own_distance():
    assert candidate_depth(SimpleNamespace(depth_is_metric=False), 4.0, _tables()) == ("network", (4.0, 0.37))
    assert candidate_depth(SimpleNamespace(depth_is_metric=True), 4.0, _tables(False),
                           ScaleConfig(depth_gt_sigma=0.01)) == ("depth_gt", (4.0, 0.01))


def test_typical_errors_within_the_tie_go_to_the_lighter_tail():
    cands = {"network": (10.0, 0.30), "ground_plane": (12.0, 0.33)}
    # ground plane's typical error 1 % under the network's: a tie, the network's lighter tail leads
    ch = combine_candidates(cands, rank={"network": 0.280, "ground_plane_network": 0.2785}, correlated=True, flags=[])
    assert ch.leader == "network"
    # 10 % under: the ground plane leads
    ch = combine_candidates(cands, rank={"network": 0.280, "ground_plane_network": 0.25}, correlated=True, flags=[])
    assert ch.leader == "ground_plane"
    # no tie margin: the least typical error leads however close
    ch = combine_candidates(cands, rank={"network": 0.280, "ground_plane_network": 0.2785}, correlated=True,
                            flags=[], config=ScaleConfig(rank_tie=0.0))
    assert ch.leader == "ground_plane"
