"""Where the measured tree stands: compass bearing from the camera, its WGS 84 position, GeoJSON.

* :func:`stem_direction` turns the rope's pixel into the stem's horizontal angle right of the
  optical axis and the horizontal part of the measured distance (level camera, or the
  calibrated pose's yaw-free frame);
* :func:`destination` moves a WGS 84 point by a distance along an azimuth: pyproj's geodesic
  (``Geod(ellps="WGS84").fwd``) when pyproj is installed (``pip install monodbh[geo]``), else
  :func:`local_destination`, a local-plane step on the ellipsoid's radii of curvature that
  agrees with the geodesic within 1 mm at 0-50 m up to latitude 70 degrees (tested);
* :func:`fill_geo` sets a row's ``stem_bearing_deg``, ``tree_lat_deg`` and ``tree_lon_deg``;
* :func:`feature_collection` / :func:`write_geojson` write the trees as RFC 7946 GeoJSON
  (Points, ``[lon, lat]``), which QGIS opens as a layer.

Imported by :mod:`monodbh.toolkit.batch` and :mod:`.results_file`; imports numpy, the standard
library and (optionally) pyproj; OpenCV through the camera's ``undistort_points``.
"""
from __future__ import annotations

import json
import math
import os
from typing import Any, Iterable, Optional

from ..result import MeasureResult
from .atomic import atomic_write_text

__all__ = ["WGS84_A", "WGS84_F", "stem_direction", "destination", "local_destination", "have_pyproj",
           "fill_geo", "tree_feature", "feature_collection", "write_geojson", "GEOJSON_DROPPED"]

#: WGS 84 semi-major axis (m) and flattening
WGS84_A = 6378137.0
WGS84_F = 1 / 298.257223563
_E2 = WGS84_F * (2 - WGS84_F)

#: row fields left out of a GeoJSON feature's properties
GEOJSON_DROPPED = ("timings_ms",)


def stem_direction(camera: Any, rope_xy: Iterable[float], distance_m: float) -> tuple[float, float]:
    """The stem's horizontal angle right of the optical axis and its horizontal distance.

    Parameters
    ----------
    camera : monodbh.calib.Camera
        The camera of the photo (already adapted with ``for_image(W, H)``), with or without pose.
    rope_xy : (2,) float
        The rope's pixel in the photo (distorted photo pixels).
    distance_m : float
        Measured distance camera to stem axis, metres (``MeasureResult.distance_m``: the
        camera-frame x-z norm).

    Returns
    -------
    offset_deg : float
        Horizontal angle from the optical axis's heading to the stem, degrees, clockwise (right)
        positive, in (-180, 180].
    horizontal_m : float
        Horizontal distance camera to stem, metres.

    Notes
    -----
    The undistorted ray ``d = (x_n, y_n, 1)`` of the rope pixel (camera frame, x right, y down,
    z forward). Without a pose the camera is taken as level: ``offset = atan2(x_n, 1)``,
    ``horizontal_m = distance_m``. With a pose, the stem point ``A = s d`` with
    ``|A_xz| = distance_m`` is rotated into the pose's yaw-free world frame
    (``Rz(-yaw) R_world_from_camera``; +x the optical axis's heading, +y left, z up):
    ``offset = atan2(-A_y, A_x)``, ``horizontal_m = hypot(A_x, A_y)``.
    """
    import numpy as np

    xy = np.asarray(list(rope_xy), np.float64).reshape(1, 2)
    xn, yn = camera.undistort_points(xy, normalized=True)[0]
    d = np.array([xn, yn, 1.0])
    pose = getattr(camera, "pose", None)
    if pose is None:
        return math.degrees(math.atan2(xn, 1.0)), float(distance_m)
    yaw = math.radians(pose.yaw_deg)
    c, s = math.cos(-yaw), math.sin(-yaw)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    A = (Rz @ np.asarray(pose.R_world_from_camera, np.float64) @ d) * (float(distance_m) / math.hypot(xn, 1.0))
    return math.degrees(math.atan2(-A[1], A[0])), float(math.hypot(A[0], A[1]))


def have_pyproj() -> bool:
    """Is pyproj importable (the ``geo`` extra)?"""
    try:
        import pyproj  # noqa: F401
    except ImportError:
        return False
    return True


def destination(lat_deg: float, lon_deg: float, azimuth_deg: float, distance_m: float) -> tuple[float, float]:
    """The WGS 84 point ``distance_m`` from ``(lat_deg, lon_deg)`` along ``azimuth_deg``.

    Parameters
    ----------
    lat_deg, lon_deg : float
        Start, degrees.
    azimuth_deg : float
        Compass bearing from true north, degrees clockwise.
    distance_m : float
        Metres along the ellipsoid.

    Returns
    -------
    (lat_deg, lon_deg) : tuple of float
        pyproj's geodesic when installed, else :func:`local_destination`.
    """
    try:
        from pyproj import Geod
    except ImportError:
        return local_destination(lat_deg, lon_deg, azimuth_deg, distance_m)
    lon, lat, _ = Geod(ellps="WGS84").fwd(lon_deg, lat_deg, azimuth_deg, distance_m)
    return float(lat), float(lon)


def local_destination(lat_deg: float, lon_deg: float, azimuth_deg: float,
                      distance_m: float) -> tuple[float, float]:
    """:func:`destination` on the local plane: north and east steps over the WGS 84 meridional
    and prime-vertical radii of curvature at the mid latitude (for distances of metres to
    hundreds of metres; see the module docstring for its accuracy).

    Returns
    -------
    (lat_deg, lon_deg) : tuple of float
    """
    north = distance_m * math.cos(math.radians(azimuth_deg))
    east = distance_m * math.sin(math.radians(azimuth_deg))
    phi0 = math.radians(lat_deg)
    phi = phi0
    for _ in range(2):                           # mid latitude: the step's second-order terms
        mid = 0.5 * (phi0 + phi)
        w = 1.0 - _E2 * math.sin(mid) ** 2
        M = WGS84_A * (1.0 - _E2) / w ** 1.5     # meridional radius of curvature
        N = WGS84_A / math.sqrt(w)               # prime-vertical radius of curvature
        phi = phi0 + north / M
    lon = math.radians(lon_deg) + east / (N * math.cos(mid))
    lon_deg_out = (math.degrees(lon) + 180.0) % 360.0 - 180.0
    return math.degrees(phi), lon_deg_out


def fill_geo(res: MeasureResult, camera: Any, width: Optional[int], height: Optional[int]) -> None:
    """Set ``stem_bearing_deg`` and the tree's position on ``res`` where they can be known.

    The bearing needs the heading, the rope pixel, the distance and the photo size; the tree's
    position also the camera's position, a true-north heading (``camera_heading_ref == "T"``)
    and no error. Anything missing, or a camera that does not fit the photo, leaves them None.

    Parameters
    ----------
    res : MeasureResult
        A row with its EXIF fields set; changed in place.
    camera : monodbh.calib.Camera
        The batch's camera (adapted here to ``width x height``).
    width, height : int or None
        The photo's size after its EXIF orientation, pixels.
    """
    if (res.camera_heading_deg is None or res.rope_xy is None or res.distance_m is None
            or not width or not height or res.error):
        return
    try:
        cam = camera.for_image(int(width), int(height))
        offset, horizontal = stem_direction(cam, res.rope_xy, float(res.distance_m))
    except Exception:  # noqa: BLE001 - a cropped photo, a camera without pixels: no bearing
        return
    if not (math.isfinite(offset) and math.isfinite(horizontal)):
        return
    res.stem_bearing_deg = (float(res.camera_heading_deg) + offset) % 360.0
    if res.camera_lat_deg is None or res.camera_lon_deg is None or res.camera_heading_ref != "T":
        return
    res.tree_lat_deg, res.tree_lon_deg = destination(res.camera_lat_deg, res.camera_lon_deg,
                                                     res.stem_bearing_deg, horizontal)


def tree_feature(row: dict) -> Optional[dict]:
    """A GeoJSON Point feature of a row (a JSON dict of :class:`MeasureResult`), or None when the
    row has no tree position. Properties: the row's fields less :data:`GEOJSON_DROPPED`."""
    lat, lon = row.get("tree_lat_deg"), row.get("tree_lon_deg")
    if lat is None or lon is None or row.get("error"):
        return None
    props = {k: v for k, v in row.items() if k not in GEOJSON_DROPPED}
    props["flags"] = list(props.get("flags") or [])
    return {"type": "Feature", "geometry": {"type": "Point", "coordinates": [float(lon), float(lat)]},
            "properties": props}


def feature_collection(rows: Iterable[dict]) -> dict:
    """RFC 7946 FeatureCollection (WGS 84, ``[lon, lat]``) of the rows with a tree position."""
    feats = [f for f in (tree_feature(r) for r in rows) if f is not None]
    return {"type": "FeatureCollection", "features": feats}


def write_geojson(path: str | os.PathLike, rows: Iterable[dict]) -> dict:
    """Write :func:`feature_collection` of ``rows`` to ``path`` atomically; returns it."""
    from .results_file import json_default

    fc = feature_collection(rows)
    atomic_write_text(path, json.dumps(fc, ensure_ascii=False, allow_nan=False, indent=1,
                                       default=json_default) + "\n")
    return fc
