"""Result records of the measuring pipeline (plain data; no heavy imports)."""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["MeasureResult", "PointCloud", "RESULT_FIELDS"]

#: Columns of the CSV / keys guaranteed in every JSON line, in order.
RESULT_FIELDS = ("photo", "dbh_cm", "dbh_sigma_cm", "distance_m", "scale_source", "flags", "error",
                 "timings_ms", "estimates_cm", "rope_xy", "tree_id",
                 # the field record (EXIF and geodesy; toolkit.photo_meta, toolkit.outputs.geo)
                 "tag", "taken_at", "camera_lat_deg", "camera_lon_deg", "camera_alt_m", "gps_accuracy_m",
                 "camera_heading_deg", "camera_heading_ref", "stem_bearing_deg", "tree_lat_deg", "tree_lon_deg")

#: decimals kept in the JSON/CSV of the float fields (7 decimals of a degree: about 1 cm)
_DECIMALS = {"dbh_cm": 2, "dbh_sigma_cm": 2, "distance_m": 3, "camera_lat_deg": 7, "camera_lon_deg": 7,
             "camera_alt_m": 2, "gps_accuracy_m": 2, "camera_heading_deg": 2, "stem_bearing_deg": 2,
             "tree_lat_deg": 7, "tree_lon_deg": 7}


@dataclass
class PointCloud:
    """Coloured points in metres, camera frame (x right, y down, z forward) unless stated.

    Attributes
    ----------
    xyz : (N, 3) float32 metres.
    rgb : (N, 3) uint8.
    tree_id : (N,) int32, 0 = not a tree (ground, sky-free background), k = tree instance k;
        the measured tree's refined cloud uses its own id.
    trunk : (N,) bool or None
        The point lies on a trunk (a tree's stem, not its limbs or foliage; the trunk network,
        else the segmenter's trunk head), None where that is not known (neither is shipped).
    """
    xyz: np.ndarray
    rgb: np.ndarray
    tree_id: np.ndarray
    trunk: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.xyz)

    @staticmethod
    def concat(clouds: list["PointCloud"]) -> "PointCloud":
        clouds = [c for c in clouds if c is not None and len(c)]
        if not clouds:
            return PointCloud(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), np.zeros(0, np.int32))
        trunk = (np.concatenate([c.trunk for c in clouds]).astype(bool)
                 if all(c.trunk is not None for c in clouds) else None)
        return PointCloud(np.concatenate([c.xyz for c in clouds]).astype(np.float32),
                          np.concatenate([c.rgb for c in clouds]).astype(np.uint8),
                          np.concatenate([c.tree_id for c in clouds]).astype(np.int32), trunk)


@dataclass
class MeasureResult:
    """One photo's measurement.

    ``dbh_cm`` is None exactly when ``error`` is set. ``flags`` are short machine-readable
    strings (e.g. ``short_arc``, ``estimators_disagree``, ``scale_from_network``).
    ``debug`` holds arrays for overlays and clouds and ``thumbnail_jpeg`` the overlay's
    thumbnail for the HTML report; neither is serialised.

    The field record (set by ``toolkit.batch.run_job`` from the photo's name and EXIF; None
    where unknown): ``tag`` (the photo's stem, or ``--tag-from``), ``taken_at`` (ISO 8601),
    the camera's WGS 84 ``camera_lat_deg``/``camera_lon_deg`` (degrees), ``camera_alt_m`` (m
    above sea level), ``gps_accuracy_m`` (horizontal error, m), ``camera_heading_deg``
    (bearing of the optical axis, degrees from ``camera_heading_ref`` north, ``"T"`` true or
    ``"M"`` magnetic), ``stem_bearing_deg`` (bearing camera to stem, same north) and the
    tree's ``tree_lat_deg``/``tree_lon_deg`` (degrees; true-north headings only).
    """
    photo: str
    dbh_cm: float | None = None
    dbh_sigma_cm: float | None = None
    distance_m: float | None = None
    scale_source: str | None = None
    flags: list[str] = field(default_factory=list)
    error: str | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    estimates_cm: dict[str, float] = field(default_factory=dict)
    rope_xy: list[float] | None = None
    tree_id: int | None = None
    debug: dict[str, Any] = field(default_factory=dict, repr=False)
    tag: str | None = None
    taken_at: str | None = None
    camera_lat_deg: float | None = None
    camera_lon_deg: float | None = None
    camera_alt_m: float | None = None
    gps_accuracy_m: float | None = None
    camera_heading_deg: float | None = None
    camera_heading_ref: str | None = None
    stem_bearing_deg: float | None = None
    tree_lat_deg: float | None = None
    tree_lon_deg: float | None = None
    #: JPEG of the overlay, downscaled (``Job.thumbnail_px``), for ``--report``; not serialised
    thumbnail_jpeg: bytes | None = field(default=None, repr=False)

    def to_json_dict(self) -> dict:
        """JSON-serialisable dict with exactly :data:`RESULT_FIELDS` (``debug`` dropped)."""
        out = {k: copy.deepcopy(getattr(self, k)) for k in RESULT_FIELDS}
        for k, n in _DECIMALS.items():
            if out[k] is not None:
                out[k] = round(float(out[k]), n)
        out["timings_ms"] = {k: round(float(v), 1) for k, v in out["timings_ms"].items()}
        out["estimates_cm"] = {k: round(float(v), 2) for k, v in out["estimates_cm"].items()}
        return out
