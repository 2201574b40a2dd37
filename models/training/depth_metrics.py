"""The standard depth metrics (AbsRel, SqRel, RMSE, RMSE-log, log10, delta < 1.25^k) of one image.

The one copy of the depth scores: the depth network's validation during training
(:mod:`.depth`) and ``dbh eval-depth`` (``monodbh.toolkit.evaluation.depth_eval``) both use it.
numpy only, so the evaluation imports it without torch. Imported by training code and the
evaluation tools; never on the measuring path.
"""
from __future__ import annotations

import numpy as np

__all__ = ["depth_metrics", "DEPTH_METRIC_KEYS"]

#: the metrics of :func:`depth_metrics`, each also with the prefix ``ms_`` (median-scaled)
DEPTH_METRIC_KEYS = ("absrel", "sqrel", "rmse", "rmse_log", "log10", "delta1", "delta2", "delta3")


def depth_metrics(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None,
                  max_depth: float = 80.0) -> dict[str, float]:
    """The depth metrics of one image, metric and median-scaled (prefix ``ms_``).

    Parameters
    ----------
    pred, gt : (H, W) float
        Predicted and true depth, metres (any equal shapes).
    valid : (H, W) bool, optional
        Pixels to score; with it or not, only pixels with ``0 < gt <= max_depth`` and a finite
        ``pred`` count.
    max_depth : float
        Farthest true depth scored, metres.

    Returns
    -------
    dict
        :data:`DEPTH_METRIC_KEYS` and their ``ms_`` twins (the prediction scaled by
        ``median(gt) / median(pred)`` first); empty when no pixel is valid. Predictions are
        clipped below at 1 mm.

    Examples
    --------
    >>> g = np.full((4, 4), 2.0)
    >>> round(depth_metrics(g * 1.1, g)["absrel"], 3), round(depth_metrics(g * 1.1, g)["ms_absrel"], 3)
    (0.1, 0.0)
    """
    m = (gt > 0) & (gt <= max_depth) & np.isfinite(pred)
    if valid is not None:
        m &= valid
    if not m.any():
        return {}
    p = np.maximum(pred[m].astype(np.float64), 1e-3)
    g = gt[m].astype(np.float64)
    out = {}
    for prefix, q in (("", p), ("ms_", p * (np.median(g) / np.median(p)))):
        ratio = np.maximum(q / g, g / q)
        out[prefix + "absrel"] = float(np.mean(np.abs(q - g) / g))
        out[prefix + "sqrel"] = float(np.mean((q - g) ** 2 / g))
        out[prefix + "rmse"] = float(np.sqrt(np.mean((q - g) ** 2)))
        out[prefix + "rmse_log"] = float(np.sqrt(np.mean((np.log(q) - np.log(g)) ** 2)))
        out[prefix + "log10"] = float(np.mean(np.abs(np.log10(q) - np.log10(g))))
        for k in (1, 2, 3):
            out[prefix + f"delta{k}"] = float(np.mean(ratio < 1.25 ** k))
    return out
