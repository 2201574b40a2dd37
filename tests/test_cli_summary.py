"""``dbh summary`` on CSVs written by the real ResultWriter: tables, --json, one-line errors."""
import json
import math
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from monodbh.cli.main import COMMANDS, app
from monodbh.toolkit.outputs.results_file import ResultWriter
from monodbh.toolkit.result import MeasureResult


def _results_csv(path, dbhs, failed=0):
    """A results CSV as ``dbh measure --csv`` writes it: one measured row per (dbh, sigma)."""
    with ResultWriter(csv_path=path) as w:
        for k, (d, s) in enumerate(dbhs):
            w.add(MeasureResult(photo=f"IMG_{k:04d}.jpg", dbh_cm=d, dbh_sigma_cm=s, distance_m=2.5,
                                scale_source="stem_base", flags=["short_arc"], timings_ms={"total": 812.0},
                                estimates_cm={"circle": d}, rope_xy=[100.0, 200.0], tree_id=1))
        for k in range(failed):
            w.add(MeasureResult(photo=f"BAD_{k}.jpg", error="no rope found", timings_ms={"total": 90.0}))
        w.finish()
    return path


def _run(*args):
    return CliRunner().invoke(app, ["summary", *[str(a) for a in args]], env={"COLUMNS": "250"})  # tmp paths are long


def _one_line_error(r, *words, code=1):
    assert r.exit_code == code, (r.exit_code, r.stdout, r.stderr)
    err = r.stderr.strip()
    assert err.startswith("error: ") and len(err.splitlines()) == 1, err
    assert "Traceback" not in r.stdout + r.stderr
    for w in words:
        assert w in err, (w, err)
    return err


@pytest.fixture()
def plot_a(tmp_path):
    return _results_csv(tmp_path / "plot_a.csv", [(10.0, 1.0), (20.0, 2.0), (30.0, 3.0)], failed=1)


def test_registered_in_the_command_table():
    assert COMMANDS["summary"] == ("summary_cmd", "summary")
    r = CliRunner().invoke(app, ["--help"])
    assert r.exit_code == 0 and "summary" in r.stdout


def test_tables_of_one_plot(plot_a):
    r = _run(plot_a, "--plot-area-m2", "400")
    assert r.exit_code == 0, r.output
    out = r.stdout
    # mean 20 ± SE 10/sqrt(3) = 5.8; QMD 21.6; BA pi/4 * 0.14 = 0.110 m^2 (±0.016, as in the library test); 75 stems/ha; 2.75 m^2/ha
    for text in ("plot_a.csv", "all plots", "20.0±5.8", "21.6", "10.0-30.0", "0.110±0.016", "75",
                 "2.75±0.39", "DBH classes", "10-15", "15-20", "30-35", "1 of 4 photos not measured"):
        assert text in out, (text, out)


def test_without_area_no_per_hectare(plot_a):
    r = _run(plot_a)
    assert r.exit_code == 0 and "/ha" not in r.stdout and "0.110±0.016" in r.stdout


def test_json_has_the_same_numbers(tmp_path, plot_a):
    b = _results_csv(tmp_path / "plot_b.csv", [(40.0, 2.0), (50.0, None)])
    out = tmp_path / "out" / "stand.json"
    r = _run(plot_a, b, "--plot-area-m2", "400", "--json", out)
    assert r.exit_code == 0, r.output
    d = json.loads(out.read_text())
    assert d["plot_area_m2"] == 400.0 and len(d["plots"]) == 2
    a = d["all_plots"]
    assert (a["plots"], a["photos"], a["trees"], a["not_measured"], a["area_m2"]) == (2, 6, 5, 1, 800.0)
    # pooled 10..50: mean 30, QMD sqrt(1100) = 33.166, BA pi/4 * 0.55 = 0.431969 m^2, 5.39961 m^2/ha,
    # 62.5 stems/ha; one tree (50 cm) without sigma
    assert a["dbh_mean_cm"] == pytest.approx(30.0)
    assert a["dbh_quadratic_mean_cm"] == pytest.approx(math.sqrt(1100))
    assert a["basal_area_m2"] == pytest.approx(0.431969, abs=1e-6)
    assert a["basal_area_m2_per_ha"] == pytest.approx(5.39961, abs=1e-5)
    assert a["stems_per_ha"] == pytest.approx(62.5) and a["trees_without_sigma"] == 1
    assert [(c["dbh_class_cm"], c["trees"]) for c in d["dbh_classes"]] == [
        ("10-15", 1), ("15-20", 0), ("20-25", 1), ("25-30", 0), ("30-35", 1), ("35-40", 0),
        ("40-45", 1), ("45-50", 0), ("50-55", 1)]
    assert "5.40" in r.stdout and "1 tree without dbh_sigma_cm" in r.stdout


def test_plot_column(tmp_path):
    p = tmp_path / "plots.csv"
    p.write_text("photo,dbh_cm,dbh_sigma_cm,error,plot\na.jpg,10,1,,P1\nb.jpg,40,,,P2\nc.jpg,30,3,,P1\n")
    out = tmp_path / "s.json"
    r = _run(p, "--json", out)
    assert r.exit_code == 0, r.output
    assert [q["plot"] for q in json.loads(out.read_text())["plots"]] == ["P1", "P2"]
    assert "P1" in r.stdout and "P2" in r.stdout


def test_empty_csv_is_a_plot_with_no_trees(tmp_path):
    p = _results_csv(tmp_path / "empty.csv", [])
    r = _run(p, "--plot-area-m2", "400")
    assert r.exit_code == 0, r.output
    assert "empty.csv" in r.stdout and "no measured trees" in r.stdout


def test_missing_file(tmp_path, plot_a):
    _one_line_error(_run(plot_a, tmp_path / "nope.csv"), "nope.csv", "no such file")


def test_no_dbh_column(tmp_path):
    p = tmp_path / "other.csv"
    p.write_text("a,b\n1,2\n")
    _one_line_error(_run(p), "other.csv", "no dbh_cm column")


@pytest.mark.parametrize("cell, problem", [("12,5", "not a number"), ("-4", "negative"),
                                           ("inf", "not finite"), ("nan", "not finite")])
def test_bad_dbh(tmp_path, plot_a, cell, problem):
    p = tmp_path / "bad.csv"
    text = plot_a.read_text().splitlines()
    cells = text[2].split(",", 2)
    text[2] = f'{cells[0]},"{cell}",{cells[2]}'
    p.write_text("\n".join(text) + "\n")
    _one_line_error(_run(p), "bad.csv", "row 3 (IMG_0001.jpg)", "dbh_cm", problem)


def test_plot_area_must_be_positive(plot_a):
    for bad in ("0", "-5", "nan", "inf"):
        r = _run(plot_a, "--plot-area-m2", bad)
        assert r.exit_code == 2 and "--plot-area-m2" in r.stderr, (bad, r.stderr)


def test_json_onto_an_input_is_refused(plot_a):
    before = plot_a.read_text()
    r = _run(plot_a, "--json", plot_a)
    _one_line_error(r, "--json", "one of the inputs", code=2)
    assert plot_a.read_text() == before


def test_json_onto_a_folder(tmp_path, plot_a):
    _one_line_error(_run(plot_a, "--json", tmp_path), "--json", "is a folder")


def test_module_imports_only_typer():
    code = ("import sys, monodbh.cli.summary_cmd; "
            "print([m for m in ('numpy', 'rich', 'monodbh.toolkit.outputs.stand') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stderr


def test_the_dbh_script_prints_one_line(tmp_path):
    """Through ``main()`` (the installed ``dbh``): one line, exit 1."""
    p = tmp_path / "bad.csv"
    p.write_text("photo,dbh_cm\na.jpg,ten\n")
    code = f"import sys; sys.argv = ['dbh', 'summary', {str(p)!r}]; from monodbh.cli.main import main; main()"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 1 and out.stderr.strip().splitlines() == [
        f"error: {p}: row 2 (a.jpg): dbh_cm 'ten' is not a number"], out.stderr


def test_the_tables_fit_80_columns(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _results_csv(tmp_path / "p07.csv", [(12.3, 0.9), (48.75, 2.4), (101.2, 6.0)], failed=2)
    r = CliRunner().invoke(app, ["summary", "p07.csv", "--plot-area-m2", "1000"], env={"COLUMNS": "80"})
    assert r.exit_code == 0, r.output
    assert "…" not in r.stdout and max(len(s) for s in r.stdout.splitlines()) <= 80, r.stdout
    assert "p07.csv" in r.stdout and "all plots" in r.stdout
