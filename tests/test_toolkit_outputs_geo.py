"""toolkit.outputs.geo: stem bearing from the rope pixel, destination point (pyproj and the local
fallback), fill_geo on a row, GeoJSON features."""
import builtins
import json
import math

import numpy as np
import pytest

from monodbh.calib import Camera, CameraPose
from monodbh.toolkit.outputs import geo
from monodbh.toolkit.result import RESULT_FIELDS, MeasureResult

pyproj = pytest.importorskip("pyproj")
GEOD = pyproj.Geod(ellps="WGS84")

W, H = 640, 480
K = [[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]]


def test_local_destination_matches_pyproj_within_a_centimetre():
    """The fallback (no pyproj) against the geodesic: 0-50 m, latitudes to +-70 deg, all azimuths."""
    worst = 0.0
    for lat in np.arange(-70.0, 70.1, 10.0):
        for lon in (-179.9999, -75.3, 0.0, 18.95, 179.9999):
            for az in np.arange(0.0, 360.0, 15.0):
                for dist in (0.0, 0.3, 1.0, 5.0, 12.5, 25.0, 50.0):
                    la, lo = geo.local_destination(lat, lon, az, dist)
                    lo2, la2, _ = GEOD.fwd(lon, lat, az, dist)
                    _, _, err = GEOD.inv(lo, la, lo2, la2)
                    worst = max(worst, err)
    print(f"worst local_destination error vs pyproj at 0-50 m, |lat| <= 70: {worst * 1000:.3f} mm")
    assert worst < 0.01


def test_local_destination_at_71_to_80_deg_still_close():
    worst = max(GEOD.inv(*geo.local_destination(lat, 10.0, az, 50.0)[::-1], *GEOD.fwd(10.0, lat, az, 50.0)[:2])[2]
                for lat in (71.0, 75.0, 80.0) for az in range(0, 360, 30))
    assert worst < 0.02


def test_destination_uses_pyproj_and_falls_back(monkeypatch):
    lat, lon = geo.destination(60.0, 25.0, 45.0, 30.0)
    lo2, la2, _ = GEOD.fwd(25.0, 60.0, 45.0, 30.0)
    assert (lat, lon) == (la2, lo2)
    real_import = builtins.__import__

    def no_pyproj(name, *a, **kw):
        if name.startswith("pyproj"):
            raise ImportError("no pyproj here")
        return real_import(name, *a, **kw)

    monkeypatch.setattr(builtins, "__import__", no_pyproj)
    assert not geo.have_pyproj()
    assert geo.destination(60.0, 25.0, 45.0, 30.0) == geo.local_destination(60.0, 25.0, 45.0, 30.0)


@pytest.mark.parametrize("angle", [-35.0, -10.0, 0.0, 5.0, 30.0])
def test_stem_direction_level_camera(angle):
    cam = Camera(K, None, (W, H))
    x = 319.5 + 800.0 * math.tan(math.radians(angle))
    off, hor = geo.stem_direction(cam, [x, 100.0], 7.5)
    assert off == pytest.approx(angle, abs=1e-9) and hor == 7.5


@pytest.mark.parametrize("pitch,roll,yaw", [(0, 0, 0), (-20, 0, 0), (15, 4, 0), (-8, -6, 30), (5, 2, -120)])
@pytest.mark.parametrize("angle", [-25.0, 0.0, 18.0])
def test_stem_direction_with_pose_and_distortion(pitch, roll, yaw, angle):
    """A stem point at known horizontal bearing and distance, projected through a distorted,
    tilted camera: the pixel and the camera-frame x-z distance give them back."""
    pose = CameraPose.from_angles(1.5, pitch, roll, yaw)
    cam = Camera(K, [-0.12, 0.03, 0.001, -0.0005, 0.0], (W, H), pose=pose)
    D, h = 8.0, 1.3 - 1.5                      # horizontal distance; rope 1.3 m above ground
    a = math.radians(yaw - angle)               # world +y is left: right of the axis is -yaw
    P_w = np.array([D * math.cos(a), D * math.sin(a), 1.5 + h])
    R = pose.R_world_from_camera
    P_c = R.T @ (P_w - pose.t_world_from_camera)
    xy = cam.project(P_c[None])[0]
    off, hor = geo.stem_direction(cam, xy, float(np.hypot(P_c[0], P_c[2])))
    assert off == pytest.approx(angle, abs=1e-6) and hor == pytest.approx(D, abs=1e-6)


def _row(**kw):
    base = dict(photo="p.jpg", dbh_cm=30.0, distance_m=6.0, rope_xy=[319.5 + 800 * math.tan(math.radians(20)), 200.0],
                camera_lat_deg=61.5, camera_lon_deg=23.75, camera_heading_deg=350.0, camera_heading_ref="T")
    base.update(kw)
    return MeasureResult(**base)


def test_fill_geo_row():
    r = _row()
    geo.fill_geo(r, Camera(K, None, (W, H)), W, H)
    assert r.stem_bearing_deg == pytest.approx(10.0)
    lo, la, _ = GEOD.fwd(23.75, 61.5, 10.0, 6.0)
    assert (r.tree_lat_deg, r.tree_lon_deg) == (pytest.approx(la, abs=1e-9), pytest.approx(lo, abs=1e-9))


def test_fill_geo_scales_the_camera_to_the_photo():
    r = _row(rope_xy=[(319.5 + 800 * math.tan(math.radians(20)) + 0.5) * 2 - 0.5, 400.0])
    geo.fill_geo(r, Camera(K, None, (W, H)), 2 * W, 2 * H)
    assert r.stem_bearing_deg == pytest.approx(10.0)


@pytest.mark.parametrize("change,bearing", [
    (dict(camera_heading_ref="M"), True), (dict(camera_heading_ref=None), True),
    (dict(camera_lat_deg=None, camera_lon_deg=None), True),
    (dict(camera_heading_deg=None), False), (dict(rope_xy=None), False), (dict(distance_m=None), False),
    (dict(error="p.jpg: no rope", dbh_cm=None), False),
])
def test_fill_geo_missing_facts(change, bearing):
    r = _row(**change)
    geo.fill_geo(r, Camera(K, None, (W, H)), W, H)
    assert (r.stem_bearing_deg is not None) == bearing
    assert r.tree_lat_deg is None and r.tree_lon_deg is None


@pytest.mark.parametrize("size", [(None, None), (0, 0), (500, 480)])  # unknown, zero, a crop
def test_fill_geo_no_size_or_cropped_photo(size):
    r = _row()
    geo.fill_geo(r, Camera(K, None, (W, H)), *size)
    assert r.stem_bearing_deg is None and r.tree_lat_deg is None


def test_feature_collection_and_file(tmp_path):
    r = _row(flags=["short_arc"], timings_ms={"total": 3.0}, estimates_cm={"circle": 30.1}, tag="T1")
    geo.fill_geo(r, Camera(K, None, (W, H)), W, H)
    rows = [r.to_json_dict(), MeasureResult(photo="e.jpg", error="e.jpg: no rope").to_json_dict(),
            MeasureResult(photo="n.jpg", dbh_cm=20.0).to_json_dict()]
    path = geo.write_geojson(tmp_path / "sub" / "trees.geojson", rows) and tmp_path / "sub" / "trees.geojson"
    fc = json.loads(path.read_text())
    assert fc["type"] == "FeatureCollection" and "crs" not in fc and len(fc["features"]) == 1
    f = fc["features"][0]
    assert f["type"] == "Feature" and f["geometry"]["type"] == "Point"
    assert f["geometry"]["coordinates"] == [rows[0]["tree_lon_deg"], rows[0]["tree_lat_deg"]]  # [lon, lat]
    assert list(f["properties"]) == [k for k in RESULT_FIELDS if k != "timings_ms"]
    assert f["properties"]["flags"] == ["short_arc"] and f["properties"]["tag"] == "T1"
    assert not list(tmp_path.joinpath("sub").glob(".*.tmp"))
    assert geo.feature_collection([]) == {"type": "FeatureCollection", "features": []}
