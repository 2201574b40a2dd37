"""toolkit.outputs.paths and the checks around it: outputs that are inputs, folders in the way,
names that fit, printable names, modes that honour the umask; tap parsing and tap ranges
(property-based); the internal-error paths of the commands."""
import os
import stat
import sys

import numpy as np
import pytest
import typer
from hypothesis import given, settings
from hypothesis import strategies as st

from monodbh.calib.errors import MonodbhError
from monodbh.toolkit.outputs.atomic import atomic_write_text
from monodbh.toolkit.outputs.paths import (InputClash, OutputPathError, check_file_target, check_not_input,
                                           ensure_folder, first_clash, fit_name, printable)

FAST = settings(max_examples=150, deadline=None)


# -- names ------------------------------------------------------------------------------------------
def test_printable_escapes_only_undecodable_bytes():
    assert printable(os.fsdecode(b"tr\xe9e_\xff.jpg")) == "tr\\xe9e_\\xff.jpg"
    assert printable("épicéa 12.jpg") == "épicéa 12.jpg"
    printable(os.fsdecode(b"\xff")).encode("utf-8")          # encodable


@FAST
@given(st.text(min_size=1, max_size=400), st.sampled_from(["_overlay.png", "_tree.ply", "_depth.npy"]))
def test_fit_name_fits_and_keeps_short_names(stem, suffix):
    name = fit_name(stem, suffix)
    assert name.endswith(suffix) and len(os.fsencode(name)) <= 231
    if len(os.fsencode(stem + suffix)) <= 231:
        assert name == stem + suffix


@FAST
@given(st.binary(min_size=1, max_size=300))
def test_fit_name_of_any_bytes_name(raw):
    name = fit_name(os.fsdecode(raw), "_overlay.png")
    assert len(os.fsencode(name)) <= 231 and os.fsencode(name).endswith(b"_overlay.png")


def test_fit_name_keeps_long_names_apart():
    a, b = fit_name("t" * 300 + "a", "_x.png"), fit_name("t" * 300 + "b", "_x.png")
    assert a != b and a.startswith("t" * 100)


# -- folders and clashes ------------------------------------------------------------------------------
def test_ensure_folder_and_file_target(tmp_path):
    assert ensure_folder(tmp_path / "a" / "b").is_dir()
    (tmp_path / "f").write_text("x")
    with pytest.raises(OutputPathError, match=r"f: not a folder \(a file of that name exists\)"):
        ensure_folder(tmp_path / "f")
    with pytest.raises(OutputPathError, match=r"f/out: not a folder .*f is a file"):
        ensure_folder(tmp_path / "f" / "out")
    with pytest.raises(OutputPathError, match=r"--csv .*f/x/out\.csv: not a folder on the way"):
        check_file_target(tmp_path / "f" / "x" / "out.csv", "--csv")
    with pytest.raises(OutputPathError, match="is a folder, not a file"):
        check_file_target(tmp_path / "a")
    assert check_file_target(tmp_path / "new" / "r.csv").parent.is_dir()


def test_check_not_input_by_any_name(tmp_path):
    photo = tmp_path / "p.jpg"
    photo.write_bytes(b"x")
    (tmp_path / "sub").mkdir()
    os.link(photo, tmp_path / "hard.csv")
    os.symlink(photo, tmp_path / "soft.csv")
    for out in (photo, tmp_path / "sub" / ".." / "p.jpg", tmp_path / "hard.csv", tmp_path / "soft.csv"):
        with pytest.raises(InputClash, match="is one of the inputs"):
            check_not_input(out, [photo], f"--csv {out}")
    check_not_input(tmp_path / "other.csv", [photo], "--csv other.csv")          # not there: fine
    assert first_clash([tmp_path / "x", tmp_path / "hard.csv"], [photo]) == (str(tmp_path / "hard.csv"), str(photo))
    assert first_clash([tmp_path / "x"], [photo]) is None


@pytest.mark.parametrize("mask", [0o022, 0o077, 0o002])
def test_atomic_writer_honours_umask_and_keeps_an_existing_mode(tmp_path, mask):
    old = os.umask(mask)
    try:
        atomic_write_text(tmp_path / "new.txt", "a")
        assert stat.S_IMODE((tmp_path / "new.txt").stat().st_mode) == 0o666 & ~mask
        (tmp_path / "kept.txt").write_text("a")
        (tmp_path / "kept.txt").chmod(0o640)
        atomic_write_text(tmp_path / "kept.txt", "b")
        assert stat.S_IMODE((tmp_path / "kept.txt").stat().st_mode) == 0o640
    finally:
        os.umask(old)


def test_atomic_writer_with_a_name_at_the_limit(tmp_path):
    name = "n" * 255
    atomic_write_text(tmp_path / name, "x")
    assert (tmp_path / name).read_text() == "x" and os.listdir(tmp_path) == [name]


# -- taps -------------------------------------------------------------------------------------------
@FAST
@given(st.text(max_size=30))
def test_parse_pick_any_text(text):
    from monodbh.cli.measure_cmd import parse_pick

    try:
        xy = parse_pick(text)
    except typer.BadParameter as exc:
        assert "\n" not in str(exc.message)
        return
    assert len(xy) == 2 and all(np.isfinite(v) and v >= 0 for v in xy)


@FAST
@given(st.floats(allow_nan=True), st.floats(allow_nan=True))
def test_parse_pick_numbers(x, y):
    from monodbh.cli.measure_cmd import parse_pick

    text = f"{x!r},{y!r}"
    ok = np.isfinite(x) and np.isfinite(y) and x >= 0 and y >= 0
    if ok:
        assert parse_pick(text) == (x, y)
    else:
        with pytest.raises(typer.BadParameter):
            parse_pick(text)


@FAST
@given(st.floats(-1e6, 1e6), st.floats(-1e6, 1e6), st.integers(64, 9000), st.integers(64, 9000),
       st.sampled_from(["pick_xy", "base_xy"]))
def test_taps_must_lie_in_the_photo(x, y, w, h, which):
    from monodbh.toolkit.pipeline import _check_taps, _Request

    req = _Request(**{which: (x, y)})
    inside = -0.5 <= x <= w - 0.5 and -0.5 <= y <= h - 0.5
    if inside:
        _check_taps("p.jpg", (h, w, 3), req)
    else:
        option = "--pick" if which == "pick_xy" else "--base"
        with pytest.raises(MonodbhError, match=rf"^p\.jpg: {option} .* is outside the {w}x{h} px photo"):
            _check_taps("p.jpg", (h, w, 3), req)


# -- the paths that catch what nobody expected ---------------------------------------------------------
def test_overlay_that_cannot_be_written_is_flagged(tmp_path):
    from monodbh.toolkit.batch import Job, output_files, run_job
    from monodbh.toolkit.result import MeasureResult

    photo = tmp_path / "p.jpg"
    photo.write_bytes(b"x")
    out = tmp_path / "out"
    overlay, _ = output_files(out, "p")
    overlay.mkdir(parents=True)                      # a folder where the overlay goes

    def fn(path, camera, **kw):
        return MeasureResult(photo=path, dbh_cm=20.0, dbh_sigma_cm=1.0,
                             debug={"image": np.zeros((64, 64, 3), np.uint8)})

    res = run_job(Job(0, str(photo), None, out_dir=str(out)), fn)
    assert res.error is None and "overlay_failed" in res.flags


def test_main_reports_an_unexpected_exception_on_one_line(monkeypatch, capsys):
    import monodbh.cli.main as m

    def boom(**kw):
        raise RuntimeError("kaput\nsecond line")

    monkeypatch.setattr(m, "app", boom)
    monkeypatch.setattr(sys, "argv", ["dbh", "measure"])
    with pytest.raises(SystemExit) as e:
        m.main()
    assert e.value.code == 3
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: internal error: RuntimeError: kaput second line")

    def bad_photo(**kw):
        raise MonodbhError("p.jpg: broken")

    monkeypatch.setattr(m, "app", bad_photo)
    with pytest.raises(SystemExit) as e:
        m.main()
    assert e.value.code == 1 and capsys.readouterr().err == "error: p.jpg: broken\n"


def test_depth_command_reports_an_unexpected_exception_and_goes_on(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    import monodbh.toolkit.evaluation.depth_eval as de
    from monodbh.cli.main import app
    from hostile_inputs import good_camera, good_photo

    a, b = good_photo(tmp_path, "a.jpg"), good_photo(tmp_path, "b.jpg")

    def photo_depth(path, camera, session):
        if path.endswith("a.jpg"):
            from monodbh.toolkit.geometry.fits import normalize
            normalize(None)
        return np.ones((4, 4), np.float32), {"depth": 1.0}

    monkeypatch.setattr(de, "photo_depth", photo_depth)
    r = CliRunner().invoke(app, ["depth", str(a), str(b), "--calib", str(good_camera(tmp_path)),
                                 "-o", str(tmp_path / "out")])
    assert r.exit_code == 1, r.output
    assert f"error: {a}: internal error in toolkit.geometry.fits:normalize: " in r.stderr
    assert (tmp_path / "out" / "b_depth.npy").is_file() and not (tmp_path / "out" / "a_depth.npy").exists()


def reconstruct_crash(path, camera, **kw):
    from monodbh.toolkit.geometry.fits import normalize

    normalize(None)


def test_reconstruct_reports_an_unexpected_exception_on_one_line(tmp_path):
    from typer.testing import CliRunner

    from monodbh.cli.main import app
    from hostile_inputs import good_camera, good_photo

    photo = good_photo(tmp_path)
    r = CliRunner().invoke(app, ["reconstruct", str(photo), "--calib", str(good_camera(tmp_path)),
                                 "-o", str(tmp_path / "s.ply"), "--measure-fn",
                                 "test_toolkit_outputs_paths:reconstruct_crash", "--session-factory", "none"])
    assert r.exit_code == 1, r.output
    assert r.stderr.startswith(f"error: {photo}: internal error in toolkit.geometry.fits:normalize: ")
    assert r.stderr.count("\n") == 1 and not (tmp_path / "s.ply").exists()
