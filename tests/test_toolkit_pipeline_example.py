"""The whole measuring pipeline with the shipped int8 models on the bundled example photo."""
import json
from pathlib import Path

import numpy as np
import pytest

from monodbh.calib import load_camera
from monodbh.toolkit import pipeline as pl

EX = Path(pl.__file__).resolve().parent / "examples"


@pytest.fixture(scope="module")
def session():
    return pl.Session()


def test_example_measured_within_its_sigma(session):
    truth = json.loads((EX / "example_truth.json").read_text())["roped_tree_dbh_cm"]
    r = pl.measure_photo(str(EX / "example.jpg"), load_camera(EX / "cam.yaml"), session=session)
    assert r.error is None, r.error
    assert 5 < r.dbh_cm < 80 and r.dbh_sigma_cm > 0
    assert abs(r.dbh_cm - truth) <= 2.5 * r.dbh_sigma_cm
    assert r.scale_source and r.distance_m > 0


def test_depth_beside_the_rope_search_changes_nothing(session, monkeypatch):
    """The segmenter and the depth network run on a background thread while the rope is searched:
    the result is the sequential one, and a failure in the thread reaches the caller as an error."""
    cam = load_camera(EX / "cam.yaml")
    monkeypatch.setattr(pl, "OVERLAP_DEPTH", False)
    seq = pl.measure_photo(str(EX / "example.jpg"), cam, session=session)
    monkeypatch.setattr(pl, "OVERLAP_DEPTH", True)
    par = pl.measure_photo(str(EX / "example.jpg"), cam, session=session)
    assert seq.error is None and par.dbh_cm == seq.dbh_cm and par.distance_m == seq.distance_m
    assert par.flags == seq.flags

    def broken(*a):
        raise pl.MonodbhError("depth network failed")
    monkeypatch.setattr(session.depth, "predict", broken)
    bad = pl.measure_photo(str(EX / "example.jpg"), cam, session=session)
    assert bad.dbh_cm is None and "depth network failed" in bad.error


def test_pick_away_from_the_rope_is_an_error_not_another_band(session):
    """A tap where there is no rope must not silently measure some band elsewhere."""
    cam = load_camera(EX / "cam.yaml")
    ok = pl.measure_photo(str(EX / "example.jpg"), cam, session=session)
    x, y = ok.rope_xy
    far = pl.measure_photo(str(EX / "example.jpg"), cam, session=session, pick_xy=(x, max(5.0, y - 300)))
    assert far.dbh_cm is None and "no red rope found at the picked point" in far.error
    # a tap on the rope measures the same tree
    r = pl.measure_photo(str(EX / "example.jpg"), cam, session=session, pick_xy=(x + 2, y + 1))
    assert r.error is None and np.isclose(r.dbh_cm, ok.dbh_cm, rtol=0.05)


def test_reported_pixels_are_the_photos_own_and_round_trip_a_tap():
    """A 12 MP photo is measured at 1600 px and undistorted: a point the pipeline reports (the
    rope, a refused band) must come back in the photo's pixels, where ``--pick`` reaches it."""
    from monodbh.calib import Camera

    W, H = 4000, 3000
    cam = Camera([[3000.0, 0, 1990.0], [0, 3000.0, 1512.0], [0, 0, 1]], [-0.06, 0.03, 1e-4, -2e-4, 0.0], (W, H))
    _, cam_work, scale, cam_dist = pl._work_image(np.zeros((H, W, 3), np.uint8), cam)
    assert max(scale) < 0.5
    for xy in [(12.0, 20.0), (2000.0, 1500.0), (3985.0, 2990.0), (300.0, 2700.0)]:
        w = pl._to_work_pixel(xy, scale, cam_dist, cam_work)
        assert np.allclose(pl._to_photo_pixel(w, scale, cam_dist, cam_work), xy, atol=0.05)
    # near a corner, dividing by the scale alone (what was reported before) is tens of pixels off
    w = pl._to_work_pixel((12.0, 20.0), scale, cam_dist, cam_work)
    assert np.hypot(*(w / np.asarray(scale) - (12.0, 20.0))) > 10
