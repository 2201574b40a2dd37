"""The whole measuring pipeline with the shipped int8 models on the bundled example photo."""
import json
from pathlib import Path

import numpy as np
import pytest

from monodbh.calib import load_camera
from monodbh.toolkit import pipeline as pl
from monodbh.toolkit.config import MeasureConfig

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
    sequential = pl.Session(config=MeasureConfig(overlap_networks=False))
    seq = pl.measure_photo(str(EX / "example.jpg"), cam, session=sequential)
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


def test_the_session_configuration_reaches_the_geometry(session):
    """A Session's MeasureConfig.geometry is the one the geometry measures with."""
    import dataclasses

    from monodbh.toolkit.geometry.config import DbhConfig, GeometryConfig
    cam = load_camera(EX / "cam.yaml")
    ok = pl.measure_photo(str(EX / "example.jpg"), cam, session=session)
    assert "few_pixels_across_stem" not in ok.flags
    strict = MeasureConfig(geometry=GeometryConfig(dbh=DbhConfig(few_pixels_px=1e6)))
    other = dataclasses.replace(session.config, geometry=strict.geometry)
    session_strict = pl.Session(config=other)
    r = pl.measure_photo(str(EX / "example.jpg"), cam, session=session_strict)
    assert "few_pixels_across_stem" in r.flags and r.dbh_cm == ok.dbh_cm


def test_idle_thread_spinning_comes_from_the_environment(monkeypatch):
    monkeypatch.setenv("MONODBH_ORT_SPIN", "1")
    assert MeasureConfig().ort_spin is True
    monkeypatch.setenv("MONODBH_ORT_SPIN", "0")
    assert MeasureConfig().ort_spin is False


@pytest.mark.parametrize("source", ["trunk_net", "trunk_head"])
def test_the_reconstructed_clouds_flag_trunk_points_and_the_measurement_is_unchanged(session, source, monkeypatch):
    """``reconstruct_photo`` flags each point on a trunk, from the trunk network where it is
    shipped, else from the segmenter's trunk head; asking for it leaves the measurement exactly
    as ``measure_photo`` gives it."""
    cam = load_camera(EX / "cam.yaml")
    assert session.trunk_net is not None and session.segmenter.has_trunk      # both shipped
    if source == "trunk_head":
        monkeypatch.setattr(session, "_trunk_net", None)
        monkeypatch.setattr(session, "_trunk_net_file", None)
        assert session.trunk_net is None
    plain = pl.measure_photo(str(EX / "example.jpg"), cam, session=session)
    res, cloud = pl.reconstruct_photo(str(EX / "example.jpg"), cam, session=session)
    assert res.dbh_cm == plain.dbh_cm and res.distance_m == plain.distance_m and res.flags == plain.flags
    assert cloud.trunk is not None and len(cloud.trunk) == len(cloud)
    tree = cloud.tree_id == res.tree_id
    # the roped tree's refined cloud is mostly its stem; the scene's trunk points are a minority
    assert cloud.trunk[tree].mean() > 0.5
    assert 0 < cloud.trunk[~tree].mean() < 0.5
