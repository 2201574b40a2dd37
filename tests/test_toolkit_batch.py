"""toolkit.batch: error rows, normalisation, ordering, writers."""
import csv
import io
import json

import numpy as np
import pytest

from monodbh.calib import MonodbhError, PhotoError
from monodbh.toolkit.batch import (Backend, BatchError, Job, ResultWriter, error_result, expand_photos,
                                   iter_results, load_object, normalise_result, run_job, unique_stems)
from monodbh.toolkit.result import RESULT_FIELDS, MeasureResult


def ok_fn(path, camera, **kw):
    if path.endswith("nope.jpg"):
        raise PhotoError(f"{path}: not an image")
    if path.endswith("crash.jpg"):
        raise ZeroDivisionError("division by zero")
    if path.endswith("weird.jpg"):
        return MeasureResult(photo="other", dbh_cm=np.float64(30.0), error="a\nb")
    return MeasureResult(photo="other", dbh_cm=np.float32(25.5), dbh_sigma_cm=1.0, timings_ms={"a": np.float64(2)})


def test_error_result_and_normalise():
    assert error_result("p", PhotoError("p: bad")).error == "p: bad"
    assert error_result("p", KeyError("k")).error == "p: internal error: KeyError: 'k'"
    r = normalise_result(MeasureResult(photo="x", dbh_cm=20.0, error="line1\n line2"), "p.jpg")
    assert r.photo == "p.jpg" and r.dbh_cm is None and r.error == "line1 line2"
    r = normalise_result(MeasureResult(photo="x"), "p.jpg")
    assert r.error.startswith("p.jpg: internal error: no DBH")
    assert normalise_result("nonsense", "p.jpg").error.startswith("p.jpg: internal error: TypeError")


def test_run_job_rows(tmp_path):
    names = ["a.jpg", "nope.jpg", "crash.jpg", "weird.jpg", "missing.jpg"]
    for n in names[:4]:
        (tmp_path / n).write_bytes(b"x")
    rows = [run_job(Job(i, str(tmp_path / n), None), ok_fn) for i, n in enumerate(names)]
    assert rows[0].error is None and rows[0].photo == str(tmp_path / "a.jpg") and "total" in rows[0].timings_ms
    assert rows[1].error.endswith("nope.jpg: not an image")
    assert rows[2].error == f"{tmp_path / 'crash.jpg'}: internal error: ZeroDivisionError: division by zero"
    assert rows[3].error == "a b" and rows[3].dbh_cm is None
    assert rows[4].error.endswith("missing.jpg: no such file")
    for r in rows:  # numpy scalars serialise
        assert list(json.loads(json.dumps(r.to_json_dict()))) == list(RESULT_FIELDS)


def library_crash_fn(path, camera, **kw):
    """A measure function whose photo ``bug.jpg`` hits an unexpected exception inside the library."""
    if path.endswith("bug.jpg"):
        from monodbh.toolkit.geometry.fits import normalize

        normalize(None)
    return MeasureResult(photo=path, dbh_cm=20.0, dbh_sigma_cm=1.0)


@pytest.mark.parametrize("workers", [1, 2])
def test_unexpected_exception_names_photo_and_stage_and_batch_goes_on(tmp_path, workers):
    for n in ("a.jpg", "bug.jpg", "c.jpg"):
        (tmp_path / n).write_bytes(b"x")
    jobs = [Job(i, str(tmp_path / n), None) for i, n in enumerate(["a.jpg", "bug.jpg", "c.jpg"])]
    rows = list(iter_results(jobs, Backend(measure="test_toolkit_batch:library_crash_fn", session=None),
                             workers=workers))
    assert [r.error is None for r in rows] == [True, False, True]
    assert rows[1].error.startswith(f"{tmp_path / 'bug.jpg'}: internal error in toolkit.geometry.fits:normalize: ")
    assert rows[2].dbh_cm == 20.0


def test_iter_results_serial_order_and_fatal(tmp_path):
    (tmp_path / "a.jpg").write_bytes(b"x")
    jobs = [Job(i, str(tmp_path / n), None) for i, n in enumerate(["a.jpg", "missing.jpg", "a.jpg"])]
    res = list(iter_results(jobs, Backend(measure="test_toolkit_batch:ok_fn", session=None)))
    assert [r.error is None for r in res] == [True, False, True]
    with pytest.raises(BatchError, match="cannot import"):
        list(iter_results(jobs, Backend(measure="nope_mod_q:f", session=None)))
    with pytest.raises(BatchError):
        load_object("no-colon")
    assert Backend(session="nope_mod_q:Session", session_optional=True).new_session() is None
    with pytest.raises(BatchError):
        Backend(session="nope_mod_q:Session").new_session()


def test_writer_csv_incremental_and_atomic_summary(tmp_path):
    stream = io.StringIO()
    w = ResultWriter(json_stream=stream, csv_path=tmp_path / "r.csv", out_dir=tmp_path / "out", meta={"calib": "c"})
    w.add(MeasureResult(photo="a", dbh_cm=20.0, flags=["x"]))
    assert len(list(csv.reader(open(tmp_path / "r.csv")))) == 2  # header + row on disk already
    w.add(error_result("b", MonodbhError("b: bad")))
    s = w.finish()
    assert s["photos"] == 2 and s["failed_photos"] == ["b"] and s["calib"] == "c"
    assert [json.loads(x)["photo"] for x in stream.getvalue().splitlines()] == ["a", "b"]
    assert len((tmp_path / "out" / "results.jsonl").read_text().splitlines()) == 2
    rows = list(csv.DictReader(open(tmp_path / "r.csv")))
    assert rows[0]["flags"] == '["x"]' and rows[1]["error"] == "b: bad" and rows[1]["dbh_cm"] == ""


def test_expand_and_unique_stems(tmp_path):
    (tmp_path / "d").mkdir()
    for n in ("b.JPG", "a.png", "notes.txt"):
        (tmp_path / "d" / n).write_bytes(b"x")
    got = expand_photos([str(tmp_path / "d"), "x/missing.jpg"])
    assert [p.rsplit("/", 1)[1] for p in got] == ["a.png", "b.JPG", "missing.jpg"]
    assert unique_stems(["a/IMG.jpg", "b/IMG.jpg", "c/IMG.png", "d/x.jpg"]) == ["IMG", "IMG_2", "IMG_3", "x"]
