"""The DBH estimators and their combination (toolkit.geometry.dbh)."""
import numpy as np
import pytest

from monodbh.toolkit.geometry import DbhConfig
from monodbh.toolkit.geometry.dbh import combine_estimates


def test_estimates_are_combined_by_inverse_variance():
    flags = []
    d, rel, est_all = combine_estimates({"tangent": 0.30, "cloud": 0.31}, {"tangent": 0.05, "cloud": 0.10},
                                        circle_as_check=False, flags=flags)
    w1, w2 = 1 / 0.05 ** 2, 1 / 0.10 ** 2
    assert d == pytest.approx((w1 * 0.30 + w2 * 0.31) / (w1 + w2), rel=1e-12)
    assert rel == pytest.approx(1 / np.sqrt(w1 + w2), rel=1e-12)
    assert set(est_all) == {"tangent", "cloud"} and flags == []


def test_far_apart_estimates_are_flagged_and_widen_the_sigma():
    flags = []
    d, rel, _ = combine_estimates({"tangent": 0.30, "cloud": 0.60}, {"tangent": 0.05, "cloud": 0.10},
                                  circle_as_check=False, flags=flags)
    assert flags == ["estimators_disagree"]
    assert rel == pytest.approx(abs(0.30 - 0.60) / d / 2)          # at least half the spread
    flags = []
    combine_estimates({"tangent": 0.30, "cloud": 0.60}, {"tangent": 0.05, "cloud": 0.10},
                      circle_as_check=False, flags=flags, config=DbhConfig(disagree_sigmas=10.0))
    assert flags == []


def test_the_circle_only_checks_a_precisely_scaled_tangent_estimate():
    flags = []
    d, rel, est_all = combine_estimates({"tangent": 0.30, "cloud": 0.60}, {"tangent": 0.05, "cloud": 0.10},
                                        circle_as_check=True, flags=flags)
    assert d == pytest.approx(0.30, rel=1e-12) and rel == pytest.approx(0.05)
    assert est_all == {"tangent": 0.30, "cloud": 0.60}
    assert flags == ["circle_as_check", "estimators_disagree"]
    # without a circle there is nothing to check
    flags = []
    assert combine_estimates({"tangent": 0.30}, {"tangent": 0.05}, circle_as_check=True, flags=flags)[0] == 0.30
    assert flags == []
