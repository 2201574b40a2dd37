"""toolkit.evaluation.ground_truth: ``dbh eval --gt-perception`` measures from the ground truth
beside each photo, through toolkit.batch, without networks."""
import json

import pytest
from typer.testing import CliRunner

pytest.importorskip("trimesh")  # the scene generator renders the samples

from monodbh.calib import load_photo  # noqa: E402
from monodbh.cli.main import app  # noqa: E402
from monodbh.toolkit.evaluation.ground_truth import measure_photo_gt, perception_from_ground_truth  # noqa: E402
from monodbh.toolkit.evaluation.synth_samples import camera_from_meta  # noqa: E402
from monodbh.toolkit.geometry import measure_from_perception  # noqa: E402

FIELDS = ("dbh_cm", "dbh_sigma_cm", "distance_m", "scale_source", "flags", "error", "estimates_cm", "rope_xy")


@pytest.fixture(scope="module")
def synth_folder(tmp_path_factory):
    from monodbh.models.synthetic import generate_sample
    from monodbh.models.synthetic.io import write_sample

    folder = tmp_path_factory.mktemp("gt_synth")
    for i in range(4):                     # seed 9000: samples 0-2 roped, 3 without a rope
        write_sample(folder, i, generate_sample(9000, i, (320, 240)))
    return folder


def _direct(folder, i):
    """What ground-truth perception measures, from the sample's files by hand."""
    from monodbh.models.synthetic.io import read_sample

    s = read_sample(folder, i)
    photo = str(folder / f"{i:06d}.jpg")
    s["rgb"] = load_photo(photo)
    cam = camera_from_meta(s["meta"]).for_image(s["rgb"].shape[1], s["rgb"].shape[0])
    perc = perception_from_ground_truth(s, cam)
    return None if perc is None else measure_from_perception(perc, photo)


def test_measure_photo_gt_is_the_perception_from_the_files(synth_folder):
    for i in range(4):
        photo = str(synth_folder / f"{i:06d}.jpg")
        meta = json.loads((synth_folder / f"{i:06d}.json").read_text())
        r = measure_photo_gt(photo, camera_from_meta(meta), pick_xy=(1.0, 2.0), want_debug=True)
        d = _direct(synth_folder, i)
        if i == 3:
            assert d is None and not meta["roped_tree"]
            assert r.error.endswith("no rope found (ground truth has none)") and r.dbh_cm is None
        else:
            assert r.dbh_cm is not None and all(getattr(r, k) == getattr(d, k) for k in FIELDS)
        assert r.timings_ms["total"] >= r.timings_ms["load"] > 0


def test_dbh_eval_gt_perception_runs_it_without_networks(synth_folder, tmp_path, monkeypatch):
    import monodbh.toolkit.pipeline as pl

    def no_networks(*a, **k):
        raise AssertionError("ground-truth perception must not load the networks")

    monkeypatch.setattr(pl, "Session", no_networks)
    rep = tmp_path / "gt.json"
    r = CliRunner().invoke(app, ["eval", str(synth_folder), "--gt-perception", "--json", str(rep),
                                 "--models-dir", str(tmp_path / "no_models")])
    assert r.exit_code == 0, r.output
    rows = json.loads(rep.read_text())["samples"]
    assert [row["sample"] for row in rows] == [0, 1, 2, 3] and json.loads(rep.read_text())["gt_perception"]
    assert [row["dbh_cm"] is not None for row in rows] == [True, True, True, False]
    assert rows[3]["error"].endswith("no rope found (ground truth has none)")
    for row in rows[:3]:
        want = _direct(synth_folder, row["sample"]).to_json_dict()
        assert {k: row[k] for k in FIELDS} == {k: want[k] for k in FIELDS}
        assert row["err_cm"] == pytest.approx(row["dbh_cm"] - row["gt_dbh_cm"])
