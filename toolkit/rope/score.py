"""The linear log-odds score of the rope detectors' logistic models (the band detector's
candidate score, the stem search's band score); imported by those two modules and by the
fitting tools.

Examples
--------
>>> linear_score({"a": 2.0, "b": 1.0, "c": 5.0}, {"bias": -1.0, "a": 0.5, "b": 2.0})
2.0
"""
from __future__ import annotations

from typing import Iterable, Mapping

__all__ = ["linear_score"]


def linear_score(features: Mapping[str, float], weights: Mapping[str, float],
                 keys: Iterable[str] | None = None) -> float:
    """``bias + sum_k w_k * f_k``, summed left to right over ``keys``.

    Parameters
    ----------
    features : feature values by name.
    weights : weights by feature name, plus an optional ``"bias"`` (0 without).
    keys : the terms in summation order. Default: the features that have a weight, in the
        order of ``features`` (the band detector's); the stem search passes its weights'
        names (every weighted feature must be present).
    """
    if keys is None:
        keys = [k for k in features if k in weights]
    return float(weights.get("bias", 0.0) + sum(weights[k] * features[k] for k in keys))
