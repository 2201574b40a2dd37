"""The geometry end to end (toolkit.geometry.measure.measure_from_perception): scale recovery,
tapped stem base, circle as check, the rope as a ruler, and the configuration passed through."""
import numpy as np
import pytest

from geometry_scenes import roped_scenes


def test_scale_recovery_and_dbh_on_a_synthetic_scene():
    """Ground-truth perception through the real geometry: the metric scale is recovered from
    the rope and the ground plane alone (the depth map is given 1.7x too far)."""
    from monodbh.toolkit.geometry import measure_from_perception

    done = 0
    for s, p in roped_scenes(21, 12):
        m = s["meta"]
        r = measure_from_perception(p)
        if r.error:
            continue
        gt = m["trees"][m["roped_tree"] - 1]
        if "ground_plane" not in r.scale_source and "stem_base" not in r.scale_source:
            continue
        assert r.distance_m == pytest.approx(gt["distance_m"], rel=0.12)
        assert r.dbh_cm == pytest.approx(100 * gt["dbh_m"], rel=0.2)
        done += 1
        if done == 1:
            break
    assert done >= 1


@pytest.mark.slow
def test_user_tapped_stem_base_sets_the_scale():
    """A tapped stem base (``--base``) gives the scale by rope-to-base metrology, whatever the
    depth map's scale; a tap above the rope is refused with a flag."""
    from monodbh.toolkit.evaluation.taps import true_base_pixel
    from monodbh.toolkit.geometry import measure_from_perception

    done = 0
    for s, p in roped_scenes(23, 16):
        m = s["meta"]
        xy, status = true_base_pixel(m, s["depth"])
        if status != "visible":
            continue
        tid = m["roped_tree"]
        # the true base is at the bottom of the roped stem's pixels
        inst = s["instance"]
        x, y = int(round(xy[0])), int(round(xy[1]))
        assert (inst[max(0, y - 4):y + 1, max(0, x - 2):x + 3] == tid).any()
        p.ground_mask = np.zeros_like(p.ground_mask)   # no ground plane, no traced base
        p.base_xy = xy
        r = measure_from_perception(p)
        if r.error:
            continue
        gt = m["trees"][tid - 1]
        assert r.scale_source.startswith("stem_base_user"), r.scale_source
        assert "stem_base_from_user" in r.flags
        assert r.distance_m == pytest.approx(gt["distance_m"], rel=0.05)
        # a "base" above the rope is no base: refused, the scale falls back to the depth map
        p.base_xy = np.asarray(r.rope_xy) - [0.0, 40.0]
        r2 = measure_from_perception(p)
        assert "stem_base_user_rejected" in r2.flags and "stem_base_user" not in (r2.scale_source or "")
        done += 1
        break
    assert done == 1


@pytest.mark.slow
def test_circle_only_checks_the_tangent_estimate():
    """Network perception: the DBH is the tangent estimate (the tree network's circle stays in
    ``estimates_cm`` as a check); with ``circle_check_only`` off, a tapped stem base still gives
    the tangent estimate and a depth-network scale combines the two."""
    from dataclasses import replace

    from monodbh.calib import Camera
    from monodbh.toolkit.geometry import GeometryConfig
    from monodbh.models.synthetic import generate_sample
    from monodbh.toolkit.evaluation.ground_truth import perception_from_ground_truth
    from monodbh.toolkit.evaluation.taps import true_base_pixel
    from monodbh.toolkit.geometry import measure_from_perception

    pytest.importorskip("embreex")
    averaged = replace(GeometryConfig(), dbh=replace(GeometryConfig().dbh, circle_check_only=False))
    done = 0
    for i in range(16):
        s = generate_sample(23, i, (640, 480))
        m = s["meta"]
        if not m["rope"] or m["rope"]["pixels"] < 60:
            continue
        xy, status = true_base_pixel(m, s["depth"])
        if status != "visible":
            continue
        cam = Camera(np.array(m["K"]), np.array(m["dist"]), (640, 480))
        p = perception_from_ground_truth(s, cam, use_silhouette=True)
        p.source = "network"
        p.depth_is_metric = False
        p.z2 = np.where(p.z2 > 0, p.z1 + 1.6 * (p.z2 - p.z1), 0)      # a circle that is too wide
        r_net = measure_from_perception(p, config=averaged)
        r_net_check = measure_from_perception(p)
        p.base_xy = xy
        r_tap = measure_from_perception(p, config=averaged)
        if r_net.error or r_tap.error or "cloud" not in r_tap.estimates_cm or "cloud" not in r_net.estimates_cm:
            continue
        assert r_tap.scale_source.startswith("stem_base_user")
        assert "circle_as_check" in r_tap.flags
        assert r_tap.dbh_cm == pytest.approx(r_tap.estimates_cm["tangent"], rel=1e-9)
        assert "circle_as_check" not in r_net.flags
        t, c = r_net.estimates_cm["tangent"], r_net.estimates_cm["cloud"]
        assert min(t, c) < r_net.dbh_cm < max(t, c)
        # by default the circle only checks, whatever leads the scale
        assert "circle_as_check" in r_net_check.flags
        assert r_net_check.dbh_cm == pytest.approx(r_net_check.estimates_cm["tangent"], rel=1e-9)
        done += 1
        break
    assert done == 1


def test_rope_of_known_diameter_sets_the_scale():
    """``--rope-mm``: a rope seen 8 px thick (its true angular thickness, as the detector reads
    it) sets the distance, with the depth map 1.7x too far; too thin or too faint a rope is
    flagged and left out."""
    from monodbh.toolkit.geometry import RopeRulerConfig, measure_from_perception

    for s, p in roped_scenes(21, 12):
        m = s["meta"]
        gt = m["trees"][m["roped_tree"] - 1]
        z_front = gt["bh_point_cam"][2] - gt["r_bh_m"]
        D = 8.0 * z_front / float(m["K"][1][1])          # the rope diameter that is 8 px at the stem's front
        p.rope_diameter_m = D
        p.rope_thickness_px = 8.0 * RopeRulerConfig().fwhm_ratio
        p.rope_contrast = 0.2
        r = measure_from_perception(p)
        if r.error:
            continue
        assert r.scale_source.startswith("rope_diameter"), r.scale_source
        assert r.distance_m == pytest.approx(gt["distance_m"], rel=0.05)
        p.rope_contrast = 0.05
        r_faint = measure_from_perception(p)
        assert "rope_too_faint_for_scale" in r_faint.flags and "rope_diameter" not in r_faint.scale_source
        p.rope_contrast, p.rope_thickness_px = 0.2, 3.0
        assert "rope_too_thin_for_scale" in measure_from_perception(p).flags
        return
    pytest.fail("no measurable roped scene")


def test_the_configuration_reaches_the_stages():
    """A configuration where no two scale sources agree: the leading source alone sets the scale
    and every other geometric source is flagged; the default combines some."""
    from monodbh.toolkit.geometry import GeometryConfig, ScaleConfig, measure_from_perception

    for s, p in roped_scenes(21, 12):
        r = measure_from_perception(p)
        if r.error or "+" not in r.scale_source:
            continue
        r0 = measure_from_perception(p, config=GeometryConfig(scale=ScaleConfig(agree_sigmas=0.0)))
        leader = r0.debug["scale_leader"]
        assert r0.scale_source == leader == r.debug["scale_leader"]
        others = [k for k in r0.debug["scale_candidates"] if k not in (leader, "network")]
        assert others and all(f"scale_disagree_{k}" in r0.flags for k in others)
        return
    pytest.fail("no scene with combined scale sources")
