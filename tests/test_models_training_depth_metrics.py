"""models.training.depth_metrics: the standard depth scores, metric and median-scaled."""
import numpy as np
import pytest

from monodbh.models.training.depth_metrics import DEPTH_METRIC_KEYS, depth_metrics


def test_scores_of_a_scaled_prediction():
    g = np.full((4, 4), 2.0)
    m = depth_metrics(g * 1.1, g)
    assert set(m) == set(DEPTH_METRIC_KEYS) | {"ms_" + k for k in DEPTH_METRIC_KEYS}
    assert m["absrel"] == pytest.approx(0.1) and m["delta1"] == 1.0 and m["ms_absrel"] == pytest.approx(0.0)
    assert m["rmse"] == pytest.approx(0.2) and m["log10"] == pytest.approx(np.log10(1.1))


def test_only_valid_pixels_count():
    g = np.array([[2.0, 0.0, 100.0, 2.0]])
    p = np.array([[2.0, 5.0, 5.0, np.nan]])
    m = depth_metrics(p, g)                               # no depth, beyond 80 m, NaN prediction: left out
    assert m["absrel"] == 0.0 and m["rmse"] == 0.0
    assert depth_metrics(p, g, valid=np.zeros_like(g, bool)) == {}
    assert depth_metrics(np.ones((2, 2)), np.zeros((2, 2))) == {}
