"""toolkit.evaluation.synth_eval: the metrics of dbh eval, its jobs and its report rows."""
import json
from pathlib import Path

import numpy as np
import pytest

from monodbh.toolkit.evaluation.synth_eval import (eval_jobs, eval_metrics, eval_record, read_eval_samples,
                                                   SampleRecordError, stage_stats)
from monodbh.toolkit.evaluation.synth_samples import on_true_rope


def test_eval_metrics_detection_and_false_positive():
    recs = [{"gt_dbh_cm": 30.0, "dbh_cm": None, "dbh_sigma_cm": None, "error": "x: no rope", "photo": "x"},
            {"gt_dbh_cm": 20.0, "dbh_cm": 22.0, "dbh_sigma_cm": 1.5, "error": None},
            {"gt_dbh_cm": None, "dbh_cm": 12.0, "dbh_sigma_cm": 1.0, "error": None}]
    m = eval_metrics(recs)
    assert m["detection_rate"] == 0.5 and m["bias_cm"] == 2.0 and m["coverage_1sigma"] == 0.0
    assert m["refusal_rate"] == 0.0 and m["false_measurements"] == 1 and m["failure_reasons"] == {"no rope": 1}


def test_eval_metrics_by_rope_thickness():
    recs = [{"gt_dbh_cm": 30.0, "gt_rope_px": 0.6, "dbh_cm": None, "error": "x: no rope", "photo": "x"},
            {"gt_dbh_cm": 30.0, "gt_rope_px": 0.9, "dbh_cm": 33.0, "dbh_sigma_cm": 2.0, "error": None},
            {"gt_dbh_cm": 20.0, "gt_rope_px": 1.5, "dbh_cm": 21.0, "dbh_sigma_cm": 2.0, "error": None},
            {"gt_dbh_cm": 20.0, "gt_rope_px": 7.0, "dbh_cm": 19.0, "dbh_sigma_cm": 2.0, "error": None},
            {"gt_dbh_cm": 20.0, "dbh_cm": 19.0, "dbh_sigma_cm": 2.0, "error": None}]   # no thickness: left out
    b = eval_metrics(recs)["by_rope_px"]
    assert list(b) == ["0-1 px", "1-2 px", ">=5 px"]
    assert b["0-1 px"] == {"roped": 2, "measured": 1, "detection_rate": 0.5, "mae_cm": 3.0}
    assert b["1-2 px"]["detection_rate"] == 1.0 and b[">=5 px"]["mae_cm"] == 1.0


def test_a_measurement_on_another_band_counts_as_a_wrong_tree(tmp_path):
    meta = {"roped_tree": 2, "width": 1280, "height": 960}
    rope = np.zeros((960, 1280), bool)
    rope[500, 300:340] = True
    inst = np.zeros((960, 1280), np.uint16)
    inst[:, 290:350] = 2
    np.savez(tmp_path / "000000.npz", rope=rope, instance=inst)
    stem = tmp_path / "000000"
    assert on_true_rope(stem, meta, (320.0, 503.0)) is True
    assert on_true_rope(stem, meta, (700.0, 500.0)) is False          # tape on another tree
    assert on_true_rope(stem, meta, None) is None
    assert on_true_rope(stem, {**meta, "roped_tree": None}, (320.0, 500.0)) is None
    m = eval_metrics([{"gt_dbh_cm": 30.0, "dbh_cm": 31.0, "dbh_sigma_cm": 2.0, "error": None, "on_true_rope": True},
                      {"gt_dbh_cm": 30.0, "dbh_cm": 45.0, "dbh_sigma_cm": 2.0, "error": None, "on_true_rope": False}])
    assert m["wrong_rope"] == 1 and m["rope_checked"] == 2


def test_stage_stats_orders_total_last_and_skips_missing():
    s = stage_stats([{"total": 10.0, "a": 1.0}, {"a": 3.0, "b": None, "total": float("nan")}, None])
    assert list(s) == ["a", "total"] and s["a"] == {"mean": 2.0, "median": 2.0, "n": 2} and s["total"]["n"] == 1


def _sample(folder, i, roped, rope_px=None):
    W, H = 80, 60
    stem = folder / f"{i:06d}"
    stem.with_suffix(".jpg").write_bytes(b"x")
    meta = {"width": W, "height": H, "K": [[60.0, 0, 40], [0, 60.0, 30], [0, 0, 1]], "dist": [0, 0, 0, 0, 0],
            "roped_tree": roped, "rope": {"tube_diameter_m": 0.01} if roped else None,
            "trees": [{"id": 1, "dbh_m": 0.3, "bh_point_cam": [0, 0, 3.1], "r_bh_m": 0.1}]}
    stem.with_suffix(".json").write_text(json.dumps(meta))
    rope = np.zeros((H, W), bool)
    if roped:
        rope[20, 30:41] = True
    np.savez(stem.with_suffix(".npz"), rope=rope, instance=np.ones((H, W), np.uint16),
             depth=np.full((H, W), 3.0, np.float32))


def test_eval_jobs_and_records_follow_the_samples(tmp_path):
    _sample(tmp_path, 0, 1)
    _sample(tmp_path, 1, None)
    samples = read_eval_samples(tmp_path, [0, 1])
    assert samples[0].gt_dbh_cm == pytest.approx(30.0) and samples[0].gt_rope_px == pytest.approx(0.2)
    assert samples[1].gt_dbh_cm is None and samples[1].gt_rope_px is None
    assert samples[0].camera.image_size == (80, 60)
    jobs = eval_jobs(samples, tap_rope=True, tap_noise_px=0.0, rope_known=True, out_dir=tmp_path / "o")
    assert [j.index for j in jobs] == [0, 1] and jobs[0].photo == str(tmp_path / "000000.jpg")
    assert jobs[0].pick_xy == (35.0, 20.0) and jobs[1].pick_xy is None       # the rope's middle pixel
    # the rope-free photo gets the marker the user carries (the roped ones' median width)
    assert jobs[0].rope_diameter_m == 0.01 and jobs[1].rope_diameter_m == pytest.approx(0.01)
    assert eval_jobs(samples[1:], rope_known=True)[0].rope_diameter_m is None     # no marker to carry
    assert eval_jobs(samples)[1].rope_diameter_m is None
    assert jobs[0].base_xy is None and jobs[0].out_dir == str(tmp_path / "o")
    # a user whose camera file holds a marker width: every photo gets it, rope-free ones too
    fixed = eval_jobs(samples, rope_mm=40.0)
    assert [j.rope_diameter_m for j in fixed] == [0.04, 0.04]
    rec = eval_record(samples[0], {"dbh_cm": 31.5, "rope_xy": [35.0, 20.0], "error": None})
    assert rec["sample"] == 0 and rec["err_cm"] == pytest.approx(1.5) and rec["on_true_rope"] is True
    rec = eval_record(samples[1], {"dbh_cm": None, "rope_xy": None, "error": "x: no rope"})
    assert rec["err_cm"] is None and rec["on_true_rope"] is None and rec["gt_dbh_cm"] is None


def test_a_bad_record_names_its_file(tmp_path):
    (tmp_path / "000003.json").write_text("{not json")
    with pytest.raises(SampleRecordError, match="000003.json: bad sample record"):
        read_eval_samples(tmp_path, [3])


def test_eval_metrics_by_base_view_counts_base_use_and_wrong_bases():
    def rec(status, src, dist_err, dbh=30.0):
        return {"gt_dbh_cm": 30.0, "dbh_cm": dbh, "dbh_sigma_cm": 2.0, "error": None, "scale_source": src,
                "gt_base_status": status, "distance_err_pct": dist_err}
    recs = [rec("visible", "stem_base+network", 2.0), rec("visible", "network", -20.0, 24.0),
            rec("occluded", "stem_base_weak", 40.0, 42.0), rec("occluded", "network", 5.0),
            rec("outside", "stem_base", -16.0), rec("outside", "rope_diameter+network", 3.0),
            rec("in_clutter", "stem_base", 20.0, 36.0),
            {"gt_dbh_cm": 30.0, "dbh_cm": None, "error": "x: no rope", "gt_base_status": "visible"}]
    m = eval_metrics(recs)
    v = m["by_base_view"]
    assert (v["visible"]["roped"], v["visible"]["measured"], v["visible"]["base_used"]) == (3, 2, 1)
    assert v["visible"]["wrong_base"] == 0 and v["visible"]["median_abs_distance_err_pct"] == 11.0
    assert (v["occluded"]["base_used"], v["occluded"]["wrong_base"]) == (1, 1)
    assert (v["outside"]["base_used"], v["outside"]["wrong_base"]) == (1, 1)
    # a base in grass is the base (imprecise, not wrong): listed apart, not counted as wrong
    assert (v["in_clutter"]["roped"], v["in_clutter"]["base_used"], v["in_clutter"]["mae_cm"]) == (1, 1, 6.0)
    assert m["wrong_base"] == 2


def _stem_meta(axis_ratio=1.0, phase=0.0, z=4.0, x=0.5):
    """A camera at the origin looking along world +y (x right, z up); a vertical stem of radius
    0.15 m whose axis passes ``x`` m right and ``z`` m ahead."""
    R = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]          # camera x, y (down), z (ahead) in the world
    return {"t_world_from_cam": [0.0, 0.0, 1.3], "R_world_from_cam": R, "roped_tree": 1,
            "trees": [{"id": 1, "axis_world": [0, 0, 1], "e1_world": [1, 0, 0], "e2_world": [0, 1, 0],
                       "position_world": [x, z, 0.0], "axis_ratio": axis_ratio, "ellipse_phase_rad": phase,
                       "harmonics": [], "r_bh_m": 0.15, "flare": 0.0, "bh_point_cam": [x, 0.0, z]}]}


def test_silhouette_of_a_round_stem_is_its_diameter_and_an_ellipse_shows_its_side():
    from monodbh.toolkit.evaluation.synth_samples import gt_silhouette

    d, dist = gt_silhouette(_stem_meta())
    assert d == pytest.approx(0.30, rel=1e-5) and dist == pytest.approx(np.hypot(0.5, 4.0))
    # an ellipse (semi-axes 0.15 and 0.075 m) seen straight ahead (x = 0): broadside along e1 shows
    # the long axis, turned 90 degrees the short one
    assert gt_silhouette(_stem_meta(0.5, 0.0, x=0.0))[0] == pytest.approx(0.30, rel=1e-3)
    assert gt_silhouette(_stem_meta(0.5, np.pi / 2, x=0.0))[0] == pytest.approx(0.15, rel=2e-3)
    assert gt_silhouette({"roped_tree": None, "trees": []}) is None


def test_width_alone_is_free_of_the_scale():
    from monodbh.toolkit.evaluation.synth_eval import EvalSample

    meta = _stem_meta()
    dist = float(np.hypot(0.5, 4.0))
    s = EvalSample(0, Path("x"), meta, None, gt_dbh_cm=30.0, gt_rope_px=2.0, gt_distance_m=4.0)
    # 20 % too far and 20 % too wide: the width itself is right
    rec = eval_record(s, {"dbh_cm": 36.0, "distance_m": 1.2 * dist, "error": None, "rope_xy": None})
    assert rec["width_err_pct"] == pytest.approx(0.0, abs=1e-3) and rec["roundness_pct"] == pytest.approx(0, abs=1e-3)
    # the right distance, 10 % too wide
    rec = eval_record(s, {"dbh_cm": 33.0, "distance_m": dist, "error": None, "rope_xy": None,
                          "estimates_cm": {"tangent": 30.0, "cloud": 36.0}})
    assert rec["width_err_pct"] == pytest.approx(10.0, abs=1e-3)
    by = rec["width_err_pct_by_estimator"]
    assert by["tangent"] == pytest.approx(0.0, abs=1e-3) and by["cloud"] == pytest.approx(20.0, abs=1e-3)
    w = eval_metrics([{**rec, "gt_dbh_cm": 30.0}])["width_by_estimator"]
    assert w["cloud"]["n"] == 1 and w["cloud"]["median_abs_pct"] == pytest.approx(20.0, abs=1e-3)
    recs = [{"gt_dbh_cm": 30.0, "dbh_cm": 30.0, "error": None, "width_err_pct": w} for w in (-1.0, 2.0, -3.0, 10.0)]
    m = eval_metrics(recs)
    assert m["width_median_abs_err_pct"] == pytest.approx(2.5) and m["width_p90_abs_err_pct"] == 10.0
    assert m["width_bias_pct"] == pytest.approx(0.5)


def test_the_error_against_the_silhouette_removes_the_stems_out_of_roundness():
    # a stem that shows 10 % wider than its tape DBH, read exactly as it shows: 10 % against the
    # tape, 0 % against the silhouette; a round stem read 5 % wide stays 5 % off
    recs = [{"gt_dbh_cm": 20.0, "dbh_cm": 22.0, "dbh_sigma_cm": 2.0, "error": None, "roundness_pct": 10.0},
            {"gt_dbh_cm": 20.0, "dbh_cm": 21.0, "dbh_sigma_cm": 2.0, "error": None, "roundness_pct": 0.0}]
    m = eval_metrics(recs)
    assert m["rel_mae_pct"] == pytest.approx(7.5)
    assert m["silhouette_rel_mae_pct"] == pytest.approx(2.5)
    assert m["roundness_mean_abs_pct"] == pytest.approx(5.0)
