"""The marker's width kept in the camera file (calib.marker) and the dbh marker command."""
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from monodbh.calib import CameraFileError, load_camera
from monodbh.calib.marker import read_marker_width_m, write_marker_width
from monodbh.cli.main import app
from monodbh.cli.marker_cmd import marker_width_m

EX = Path(__file__).resolve().parents[1] / "toolkit" / "examples"


@pytest.fixture
def cam(tmp_path):
    p = tmp_path / "cam.yaml"
    shutil.copy(EX / "cam.yaml", p)
    return p


def test_set_read_clear_keeps_the_rest_of_the_file(cam):
    before = cam.read_text()
    assert read_marker_width_m(cam) is None
    write_marker_width(cam, 12.5)
    assert read_marker_width_m(cam) == pytest.approx(0.0125)
    assert cam.read_text().startswith(before.rstrip("\n"))
    write_marker_width(cam, 40)                          # replaced, not appended twice
    assert cam.read_text().count("marker_width_mm") == 1 and read_marker_width_m(cam) == pytest.approx(0.040)
    c0, c1 = load_camera(EX / "cam.yaml"), load_camera(cam)   # the camera is untouched
    assert (c0.K == c1.K).all() and (c0.dist == c1.dist).all() and c0.image_size == c1.image_size
    write_marker_width(cam, None)
    assert read_marker_width_m(cam) is None and cam.read_text() == before


def test_bad_widths_and_files_are_one_line_errors(cam, tmp_path):
    with pytest.raises(CameraFileError, match="between 1 and 100 mm"):
        write_marker_width(cam, 0.2)
    cam.write_text(cam.read_text() + "marker_width_mm: thick\n")
    with pytest.raises(CameraFileError, match=r"cam.yaml: 'marker_width_mm' must be a number"):
        read_marker_width_m(cam)
    other = tmp_path / "notes.yaml"
    other.write_text("a: 1\n")
    with pytest.raises(CameraFileError, match="notes.yaml: missing key 'camera_matrix'"):
        write_marker_width(other, 10)
    assert other.read_text() == "a: 1\n"                 # never replaced by a half-written file


def test_rope_mm_overrides_the_camera_file(cam):
    assert marker_width_m(cam, None) == (None, None)
    write_marker_width(cam, 10)
    assert marker_width_m(cam, None) == (pytest.approx(0.010), str(cam))
    assert marker_width_m(cam, 25.0) == (pytest.approx(0.025), "--rope-mm")


def test_dbh_marker_command(cam):
    r = CliRunner().invoke(app, ["marker", str(cam), "--width-mm", "10"])
    assert r.exit_code == 0 and "marker width 10 mm" in r.output
    r = CliRunner().invoke(app, ["marker", str(cam)])
    assert r.exit_code == 0 and "marker width 10 mm" in r.output
    r = CliRunner().invoke(app, ["marker", str(cam), "--clear"])
    assert r.exit_code == 0 and "no marker width" in r.output and read_marker_width_m(cam) is None
    r = CliRunner().invoke(app, ["marker", str(cam), "--width-mm", "10", "--clear"])
    assert r.exit_code == 2


def test_the_retake_hint_names_what_to_do():
    from monodbh.cli.measure_cmd import retake_hint
    no_marker = retake_hint(1, 3, marker_known=False)
    assert "1 of 3" in no_marker and "foot" in no_marker and "--width-mm" in no_marker
    assert "5 px" in retake_hint(1, 1, marker_known=True)
