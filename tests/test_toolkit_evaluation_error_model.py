"""The measured error model: tail-aware sigmas, stored per shipped-model set in the manifest."""
import json
import shutil

import numpy as np
import pytest

from monodbh.toolkit.evaluation.error_model import sigma_table, tail_sigma, write_manifest_error_model


def test_tail_sigma_gaussian_and_heavy_tail():
    rng = np.random.default_rng(0)
    g = rng.normal(0, 0.1, 4000)
    assert tail_sigma(g) == pytest.approx(0.1, rel=0.06)
    heavy = np.r_[rng.normal(0, 0.1, 800), rng.normal(0, 0.6, 200)]     # 20 % outliers
    s = tail_sigma(heavy)
    assert s > 0.15 and np.mean(np.abs(heavy) <= 2 * s) >= 0.9


def test_sigma_table_keys_and_min_n():
    rows = [dict(dbh_cm=30.0, cand_log_err={"network": 0.1 * (-1) ** i, "stem_base": 0.5},
                 est_angular_log_err={"tangent": 0.05, "cloud": -0.2}) for i in range(10)]
    rows[0]["cand_log_err"].pop("stem_base")
    t = sigma_table(rows, min_n=10)
    assert set(t) == {"network", "width", "cloud"}            # stem_base measured 9 times only
    assert t["network"] == pytest.approx(0.1 / 0.674, rel=1e-6)


def test_session_uses_error_model_only_for_its_models(tmp_path):
    from monodbh.models.runtime import MANIFEST_PATH
    from monodbh.toolkit.pipeline import Session

    src = MANIFEST_PATH.parent
    for f in src.glob("*.onnx"):
        (tmp_path / f.name).symlink_to(f)
    shutil.copy(MANIFEST_PATH, tmp_path / "manifest.json")
    sig = {"network": 0.2, "width": 0.1}
    write_manifest_error_model(sig, "data/calset", 42, tmp_path / "manifest.json")
    s = Session(tmp_path)
    assert s.sigma_network == sig and not s.error_model_stale
    man = json.loads((tmp_path / "manifest.json").read_text())
    man["models"]["depth"]["sha256"] = "0" * 64                # the depth network was retrained
    (tmp_path / "manifest.json").write_text(json.dumps(man))
    s = Session(tmp_path)
    assert s.sigma_network is None and s.error_model_stale
    # measured with the depth network run differently (no mirror-image averaging): stale too
    write_manifest_error_model(sig, "data/calset", 42, tmp_path / "manifest.json")
    man = json.loads((tmp_path / "manifest.json").read_text())
    assert man["error_model"]["depth_flip_tta"] is True
    man["error_model"]["depth_flip_tta"] = False
    (tmp_path / "manifest.json").write_text(json.dumps(man))
    assert Session(tmp_path).error_model_stale


def test_distance_calibration_fit_recovers_a_shrinkage():
    """Network distances scattered twice as widely (in log) as the truth around 4 m: the fit
    finds b ~ 0.5 and shrinks them back; rows led by a precise source are left out."""
    from monodbh.toolkit.evaluation.error_model import distance_calibration_fit
    rng = np.random.default_rng(0)
    true = np.exp(rng.uniform(np.log(1.5), np.log(12), 200))
    net = np.exp(np.log(4.0) + 2.0 * (np.log(true) - np.log(4.0)) + rng.normal(0, 0.02, 200))
    rows = [dict(dbh_cm=20.0, scale_leader="network", lam_true=float(t), lam_combined_log_err=float(np.log(n / t)))
            for t, n in zip(true, net)]
    rows += [dict(dbh_cm=20.0, scale_leader="stem_base_user", lam_true=5.0, lam_combined_log_err=1.0)] * 50
    fit = distance_calibration_fit(rows)
    assert fit["n"] == 200
    assert fit["b"] == pytest.approx(0.5, abs=0.02)
    assert fit["fixed_point_m"] == pytest.approx(4.0, rel=0.05)
    assert fit["median_abs_ln_after"] < 0.05 < fit["median_abs_ln_before"]
    assert 0 < fit["sigma"] < 0.05
    assert distance_calibration_fit(rows[:10]) is None


def test_error_model_summary_statistics():
    from monodbh.toolkit.evaluation.error_model import summarize
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


def test_collect_in_two_processes_gives_the_rows_in_sample_order(tmp_path):
    pytest.importorskip("trimesh")
    from monodbh.models.synthetic.dataset import synthesize
    from monodbh.toolkit.evaluation.error_model import collect
    synthesize(tmp_path, 3, seed=9000, size=(640, 480), workers=1)
    one = collect(tmp_path, progress=False)
    two = collect(tmp_path, progress=False, jobs=2)
    assert [r["photo"] for r in two] == [r["photo"] for r in one] and len(one) >= 2
    for a, b in zip(one, two):
        assert (a.get("dbh_cm") is None) == (b.get("dbh_cm") is None)
        if a.get("dbh_cm") is not None:
            assert b["dbh_cm"] == pytest.approx(a["dbh_cm"], rel=0.02)
