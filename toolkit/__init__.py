"""The measuring library that ``dbh measure`` runs: rope finding, scale, unprojection, DBH, outputs.

Public API (loaded on first use, so ``import monodbh.toolkit`` stays light)::

    from monodbh.calib import load_camera
    from monodbh.toolkit import Session, measure_photo

    session = Session()                      # loads the shipped ONNX networks once
    res = measure_photo("IMG_0412.jpg", load_camera("cam.yaml"), session=session)
    print(res.dbh_cm, res.dbh_sigma_cm, res.flags)

- :func:`measure_photo`, :func:`reconstruct_photo` and :class:`Session` (:mod:`.pipeline`);
- :class:`MeasureConfig` (:mod:`.config`), every tuning parameter with its default;
- :class:`MeasureResult` and :class:`PointCloud` (:mod:`.result`);
- :func:`detect_rope`, :class:`RopeCandidate`, :class:`RopeDetection` (:mod:`.rope`).

Subpackages: :mod:`.rope` (finding the rope: one module per detector and the ``select`` step),
:mod:`.geometry` (up direction, stem base, scale candidates, DBH), :mod:`.outputs` (overlay,
point clouds, results files). :mod:`.evaluation` holds the benchmark, fitting and ground-truth
tools; nothing here imports it.

Imported by ``monodbh.cli``; imports ``monodbh.calib`` and ``monodbh.models.runtime`` only
(never training, export or the scene generator).
"""
from __future__ import annotations

import importlib
from typing import Any

__all__ = ["measure_photo", "reconstruct_photo", "Session", "MeasureConfig", "MeasureResult",
           "PointCloud", "detect_rope", "RopeCandidate", "RopeDetection"]

_WHERE = {
    "measure_photo": ".pipeline", "reconstruct_photo": ".pipeline", "Session": ".pipeline",
    "MeasureConfig": ".config", "MeasureResult": ".result", "PointCloud": ".result",
    "detect_rope": ".rope", "RopeCandidate": ".rope", "RopeDetection": ".rope",
}


def __getattr__(name: str) -> Any:
    """Import a public name's module on first access (PEP 562)."""
    if name in _WHERE:
        value = getattr(importlib.import_module(_WHERE[name], __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
