"""Metric geometry of the measuring pipeline: circle fits on partial arcs, planes, metrology,
tangent-ray DBH, stem edges, and scale recovery on a synthetic scene."""
import numpy as np
import pytest

from monodbh.toolkit.geometry import (fit_circle, fit_plane_ransac, metrology_distance, normalize,
                                      tangent_diameter)


@pytest.mark.parametrize("arc_deg", [90, 120, 180, 270])
def test_circle_fit_partial_arc_is_unbiased(arc_deg):
    rng = np.random.default_rng(1)
    r, c = 0.15, np.array([0.3, 5.0])
    t = np.linspace(-np.radians(arc_deg) / 2, np.radians(arc_deg) / 2, 80) - np.pi / 2
    P = c + r * np.c_[np.cos(t), np.sin(t)] + rng.normal(0, 0.0015, (80, 2))
    # outliers (bark flakes, background) must not matter
    P = np.concatenate([P, c + rng.uniform(-0.5, 0.5, (12, 2))])
    f = fit_circle(P, threshold=0.005)
    assert f
    assert f.r == pytest.approx(r, rel=0.03 if arc_deg >= 120 else 0.06)
    assert np.hypot(f.xc - c[0], f.yc - c[1]) < 0.01
    assert abs(f.arc_deg - arc_deg) < 15


def test_circle_fit_failure_is_falsy():
    f = fit_circle(np.zeros((3, 2)), threshold=0.01)
    assert not f and "slice points" in f.reason


def test_plane_ransac_recovers_ground_with_outliers():
    rng = np.random.default_rng(0)
    n = normalize(np.array([0.05, -1.0, 0.2]))       # camera frame: up is -y
    h = 1.5
    # points on n.X + h = 0
    a = normalize(np.cross(n, [1, 0, 0]))
    b = np.cross(n, a)
    uv = rng.uniform(-5, 5, (500, 2))
    P = -h * n + uv[:, :1] * a + uv[:, 1:] * b + rng.normal(0, 0.01, (500, 3))
    P = np.concatenate([P, rng.uniform(-5, 5, (150, 3))])
    pl = fit_plane_ransac(P, threshold=0.03)
    assert pl
    assert abs(abs(pl.n @ n) - 1) < 1e-3
    assert pl.c == pytest.approx(h, abs=0.01)


def test_metrology_recovers_distance():
    up = normalize(np.array([0.0, -1.0, 0.05]))
    base = np.array([0.4, 1.5, 6.0])
    top = base + 1.3 * up
    lt, lb, res = metrology_distance(normalize(top), normalize(base), up, 1.3)
    assert lt == pytest.approx(np.linalg.norm(top), rel=1e-9)
    assert lb == pytest.approx(np.linalg.norm(base), rel=1e-9)
    assert res < 1e-9


def test_tangent_diameter_of_a_cylinder():
    axis = normalize(np.array([0.02, -1.0, 0.01]))
    C = np.array([0.3, 0.2, 5.0])
    rho = 0.17
    # tangent points of the circle seen from the origin, in the cross-section plane
    Cp = C - (C @ axis) * axis
    D = np.linalg.norm(Cp)
    e1 = Cp / D
    e2 = np.cross(axis, e1)
    ang = np.arcsin(rho / D)
    rays = [np.cos(ang) * e1 + s * np.sin(ang) * e2 + 0.1 * axis for s in (-1, 1)]
    assert tangent_diameter(rays[0], rays[1], axis, C) == pytest.approx(2 * rho, rel=1e-9)


def _roped_scenes(seed: int, n: int):
    """Synthetic 640x480 scenes with a well-visible rope: ``(sample, perception)`` with
    ground-truth masks and a depth map 1.7x too far (wrong scale, as a network's would be)."""
    pytest.importorskip("embreex")
    from monodbh.calib import Camera
    from monodbh.models.synthetic import generate_sample
    from monodbh.toolkit.gt import perception_from_ground_truth

    for i in range(n):
        s = generate_sample(seed, i, (640, 480))
        m = s["meta"]
        if not m["rope"] or m["rope"]["pixels"] < 60:
            continue
        cam = Camera(np.array(m["K"]), np.array(m["dist"]), (640, 480))
        p = perception_from_ground_truth(s, cam, use_silhouette=False)
        p.depth = p.depth * 1.7
        p.depth_is_metric = False
        yield s, p


def test_scale_recovery_and_dbh_on_a_synthetic_scene():
    """Ground-truth perception through the real geometry: the metric scale is recovered from
    the rope and the ground plane alone (the depth map is given 1.7x too far)."""
    from monodbh.toolkit.measure_core import measure_from_perception

    done = 0
    for s, p in _roped_scenes(21, 12):
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


def test_user_tapped_stem_base_sets_the_scale():
    """A tapped stem base (``--base``) gives the scale by rope-to-base metrology, whatever the
    depth map's scale; a tap above the rope is refused with a flag."""
    from monodbh.toolkit.gt import true_base_pixel
    from monodbh.toolkit.measure_core import measure_from_perception

    done = 0
    for s, p in _roped_scenes(23, 16):
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


def test_unproject_depth_matches_pinhole():
    from monodbh.toolkit.pipeline import unproject_depth
    K = np.array([[500.0, 0, 160], [0, 480.0, 120], [0, 0, 1]])
    z = np.full((240, 320), 4.0, np.float32)
    z[100:, :] = 7.5
    for step in (1, 2):
        pts = unproject_depth(z, K, step)
        assert pts.shape == (240 // step, 320 // step, 3)
        v, u = 150 // step, 40 // step
        zz = z[v * step, u * step]
        np.testing.assert_allclose(pts[v, u], [(u * step - 160) / 500 * zz, (v * step - 120) / 480 * zz, zz],
                                   rtol=0, atol=0.02 * step)


def test_error_model_summary_statistics():
    from monodbh.toolkit.error_model import summarize
    rows = [dict(photo=str(i), true_dbh_cm=20.0, dbh_cm=20.0 * np.exp(e), dbh_sigma_cm=2.0,
                 scale_log_err=e, cand_log_err={"network": e, "ground_plane": -e},
                 cand_sigma={"network": 0.3, "ground_plane": 0.4}, est_angular_log_err={"tangent": 0.0})
            for i, e in enumerate([0.05, -0.1, 0.2, 0.0])]
    rows.append(dict(photo="x", true_dbh_cm=30.0, error="no red rope found"))
    s = summarize(rows)
    assert s["n_roped"] == 5 and s["n_measured"] == 4
    assert s["sources"]["network"]["median_abs"] == pytest.approx(0.075)
    assert s["sources"]["ground_plane"]["bias"] == pytest.approx(-0.025)
    assert s["sources"]["network"]["sigma"] == pytest.approx(0.075 / 0.674)
    errs = np.abs(20.0 * np.exp([0.05, -0.1, 0.2, 0.0]) - 20.0)
    assert s["dbh_mae_cm"] == pytest.approx(errs.mean())
    assert s["coverage_1sigma"] == pytest.approx(np.mean(errs <= 2.0))


def test_circle_only_checks_the_tangent_estimate_when_the_scale_is_precise():
    """Network perception: with a tapped stem base the DBH is the tangent estimate (the tree
    network's circle stays in ``estimates_cm`` as a check); with a depth-network scale the two
    are combined."""
    from monodbh.calib import Camera
    from monodbh.models.synthetic import generate_sample
    from monodbh.toolkit.gt import perception_from_ground_truth, true_base_pixel
    from monodbh.toolkit.measure_core import measure_from_perception

    pytest.importorskip("embreex")
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
        r_net = measure_from_perception(p)
        p.base_xy = xy
        r_tap = measure_from_perception(p)
        if r_net.error or r_tap.error or "cloud" not in r_tap.estimates_cm or "cloud" not in r_net.estimates_cm:
            continue
        assert r_tap.scale_source.startswith("stem_base_user")
        assert "circle_as_check" in r_tap.flags
        assert r_tap.dbh_cm == pytest.approx(r_tap.estimates_cm["tangent"], rel=1e-9)
        assert "circle_as_check" not in r_net.flags
        t, c = r_net.estimates_cm["tangent"], r_net.estimates_cm["cloud"]
        assert min(t, c) < r_net.dbh_cm < max(t, c)
        done += 1
        break
    assert done == 1


def test_rope_of_known_diameter_sets_the_scale():
    """``--rope-mm``: a rope seen 8 px thick (its true angular thickness, as the detector reads
    it) sets the distance, with the depth map 1.7x too far; too thin or too faint a rope is
    flagged and left out."""
    from monodbh.toolkit import measure_core as mc

    for s, p in _roped_scenes(21, 12):
        m = s["meta"]
        gt = m["trees"][m["roped_tree"] - 1]
        z_front = gt["bh_point_cam"][2] - gt["r_bh_m"]
        D = 8.0 * z_front / float(m["K"][1][1])          # the rope diameter that is 8 px at the stem's front
        p.rope_diameter_m = D
        p.rope_thickness_px = 8.0 * mc.ROPE_RULER_FWHM_RATIO
        p.rope_contrast = 0.2
        r = mc.measure_from_perception(p)
        if r.error:
            continue
        assert r.scale_source.startswith("rope_diameter"), r.scale_source
        assert r.distance_m == pytest.approx(gt["distance_m"], rel=0.05)
        p.rope_contrast = 0.05
        r_faint = mc.measure_from_perception(p)
        assert "rope_too_faint_for_scale" in r_faint.flags and "rope_diameter" not in r_faint.scale_source
        p.rope_contrast, p.rope_thickness_px = 0.2, 3.0
        assert "rope_too_thin_for_scale" in mc.measure_from_perception(p).flags
        return
    pytest.fail("no measurable roped scene")


def test_stem_depth_is_the_nearest_across_the_stem():
    import cv2

    from monodbh.toolkit.measure_core import _depth_nearest_across

    # the photo's edges say the stem spans x 34-45; the network's map (coarse, upsampled) has
    # the stem narrower and shifted: its middle reads the background, the nearest depth the stem
    d = np.full((60, 80), 10.0, np.float32)
    d[:, 31:39] = 5.0
    blurred = cv2.GaussianBlur(d, (0, 0), 1.5)
    assert blurred[30, 40] > 8.0
    z = _depth_nearest_across(blurred, (34.0, 30.0), (45.0, 30.0))
    assert z == pytest.approx(float(blurred[30, 35:39].min()), abs=1e-6) and z < 5.1
    # the cross-section may lean: the segment between the edges is followed, +-2 px across
    assert _depth_nearest_across(d, (34.0, 28.0), (45.0, 32.0)) == pytest.approx(5.0)
    # nothing positive there (or off the map): nan, not a number that looks like a depth
    assert np.isnan(_depth_nearest_across(np.zeros_like(d), (34.0, 30.0), (45.0, 30.0)))
    assert np.isnan(_depth_nearest_across(d, (200.0, 300.0), (210.0, 300.0)))
