"""Acceptance on OpenCV's sample chessboard photos (left01..14, no 10; 640x480, 9x6 corners).

See ``<shared data>/opencv_chessboard/MANIFEST.md`` for the reference values:
* OpenCV's CI test (``modules/python/test/test_calibration.py``): classic detector,
  ``cornerSubPix((5, 5), EPS+COUNT 30 0.1)``, square 1.0, flags 0 -> RMS 0.196334638 and
  K = [[532.80992189, 0, 342.4952186], [0, 532.93346422, 233.8879292]] (tolerance |RMS| < 0.01,
  here L1(K) < 1).
* OpenCV's calibration sample output ``reference/left_intrinsics.yml``: fx = 535.9157.
"""
import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from monodbh.calib import Board, calibrate, load_camera, save_camera
from monodbh.cli.main import app

TEST_K = np.array([[532.80992189, 0.0, 342.4952186], [0.0, 532.93346422, 233.8879292],
                   [0.0, 0.0, 1.0]])
TEST_RMS = 0.196334638
SAMPLE_FX = 535.91573396163199


@pytest.fixture(scope="module")
def left_images(shared_data):
    d = shared_data / "opencv_chessboard"
    files = sorted(d.glob("left*.jpg"))
    if len(files) != 13:
        pytest.skip(f"expected 13 left*.jpg in {d}, found {len(files)}")
    return files


def test_opencv_ci_procedure_reproduces_published_values(left_images):
    res = calibrate(left_images, Board(9, 6, 1.0), detector="classic", subpix_win=5,
                    subpix_iters=30, subpix_eps=0.1, flags=0, reject_outliers=False)
    assert len(res.used) == 13
    assert abs(res.rms - TEST_RMS) < 0.01
    assert np.abs(res.camera.K - TEST_K).sum() < 1.0


@pytest.fixture(scope="module")
def cli_run(left_images, tmp_path_factory):
    out = tmp_path_factory.mktemp("cli")
    cam = out / "cam.yaml"
    r = CliRunner().invoke(app, ["calibrate", *map(str, left_images), "--board", "9x6",
                                 "--square", "0.025", "-o", str(cam), "--json",
                                 "--debug-dir", str(out / "debug")])
    assert r.exit_code == 0, r.stderr
    return cam, json.loads(r.stdout), r.stderr, out


def test_default_procedure_matches_opencv_sample(cli_run):
    cam_path, summary, report, _ = cli_run
    cam = load_camera(cam_path)
    assert abs(cam.fx / SAMPLE_FX - 1) < 0.01
    assert abs(cam.fy / SAMPLE_FX - 1) < 0.01
    assert summary["rms_px"] < 0.45
    assert summary["views_used"] + summary["views_rejected"] == 13
    assert abs(cam.cx - 342.28) < 3 and abs(cam.cy - 235.57) < 3
    # The report on stderr carries the essentials.
    for word in ("views:", "RMS reprojection error", "fx =", "±", "coverage", "wrote"):
        assert word in report


def test_debug_overlays_written(cli_run):
    *_, out = cli_run
    files = sorted((out / "debug").glob("*.jpg"))
    assert len(files) == 13
    img = cv2.imread(str(files[0]))
    assert img is not None and max(img.shape[:2]) >= 1280


def test_cli_output_round_trips(cli_run, left_images, tmp_path):
    cam_path, summary, _, _ = cli_run
    text = cam_path.read_text()
    assert text.startswith("%YAML:1.0\n")
    for key in ("calibration_time", "nframes", "image_width", "image_height", "board_width",
                "board_height", "square_size", "flags", "camera_matrix",
                "distortion_coefficients", "avg_reprojection_error",
                "per_view_reprojection_errors"):
        assert f"\n{key}:" in text, key
    cam = load_camera(cam_path)
    fs = cv2.FileStorage(str(cam_path), cv2.FILE_STORAGE_READ)
    assert np.array_equal(fs.getNode("camera_matrix").mat(), cam.K)
    assert np.array_equal(fs.getNode("distortion_coefficients").mat().ravel(), cam.dist)
    assert fs.getNode("avg_reprojection_error").real() == cam.info.avg_reprojection_error
    assert np.array_equal(fs.getNode("per_view_reprojection_errors").mat().ravel(),
                          cam.info.per_view_reprojection_errors)
    assert int(fs.getNode("nframes").real()) == summary["views_used"]
    fs.release()
    assert np.allclose(cam.K, summary["K"], rtol=0, atol=0)
    # Same numbers as ROS camera_info load to the same K.
    save_camera(cam, tmp_path / "ros.yaml", format="ros")
    ros = load_camera(tmp_path / "ros.yaml")
    assert np.array_equal(ros.K, cam.K) and np.array_equal(ros.dist, cam.dist)
    # And `dbh calibrate --format ros` writes a ROS file directly.
    r = CliRunner().invoke(app, ["calibrate", *map(str, left_images), "--board", "9x6",
                                 "--square", "0.025", "-o", str(tmp_path / "c.yaml"),
                                 "--format", "ros"])
    assert r.exit_code == 0, r.stderr
    # A second calibration run is not bit-identical across machines (OpenCV's parallel
    # Levenberg-Marquardt sums in thread order): 1e-6 relative is 0.5 milli-pixel here.
    assert np.allclose(load_camera(tmp_path / "c.yaml").K, cam.K, rtol=1e-6, atol=0)

