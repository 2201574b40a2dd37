"""Bad input to ``dbh calibrate`` / ``dbh calibrate-pose``: one-line ``error:``, exit 1, no traceback."""
import re
import subprocess
import sys

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from monodbh.calib import Camera
from monodbh.cli.main import app

BOARD = ["--board", "9x6", "--square", "0.025"]


def _board_image(angle=0.0, size=(640, 480), sq=40):
    """A plain 9x6 (inner corners) chessboard, rotated by ``angle`` degrees."""
    w, h = size
    img = np.full((h, w), 235, np.uint8)
    x0, y0 = (w - 10 * sq) // 2, (h - 7 * sq) // 2
    for j in range(7):
        for i in range(10):
            if (i + j) % 2 == 0:
                img[y0 + j * sq:y0 + (j + 1) * sq, x0 + i * sq:x0 + (i + 1) * sq] = 20
    M = cv2.getRotationMatrix2D((w / 2, h / 2), angle, 0.9)
    return cv2.warpAffine(img, M, (w, h), borderValue=235)


def _run(args):
    r = CliRunner().invoke(app, [str(a) for a in args])
    return r


def _assert_one_line_error(r, *words):
    assert r.exit_code == 1, (r.exit_code, r.stdout, r.stderr)
    err = r.stderr.strip()
    assert err.startswith("error: "), err
    assert len(err.splitlines()) == 1, err
    assert "Traceback" not in r.stderr + r.stdout
    for w in words:
        assert w in err, (w, err)
    return err


@pytest.fixture()
def boards(tmp_path):
    paths = []
    for k, a in enumerate((0.0, 8.0, -12.0)):
        p = tmp_path / f"board{k}.png"
        cv2.imwrite(str(p), _board_image(a))
        paths.append(p)
    return paths


def test_empty_file(tmp_path, boards):
    p = tmp_path / "empty.jpg"
    p.write_bytes(b"")
    _assert_one_line_error(_run(["calibrate", *boards, p, *BOARD, "-o", tmp_path / "c.yaml"]),
                           "empty.jpg", "empty")
    assert not (tmp_path / "c.yaml").exists()


def test_truncated_jpeg(tmp_path, boards):
    good = tmp_path / "full.jpg"
    cv2.imwrite(str(good), _board_image(), [cv2.IMWRITE_JPEG_QUALITY, 90])
    p = tmp_path / "cut.jpg"
    p.write_bytes(good.read_bytes()[:3000])
    _assert_one_line_error(_run(["calibrate", *boards, p, *BOARD, "-o", tmp_path / "c.yaml"]),
                           "cut.jpg", "truncated")


def test_text_file_named_jpg(tmp_path, boards):
    p = tmp_path / "readme.jpg"
    p.write_text("hello, I am not a photo\n")
    _assert_one_line_error(_run(["calibrate", *boards, p, *BOARD, "-o", tmp_path / "c.yaml"]),
                           "readme.jpg", "not an image")


def test_missing_file(tmp_path):
    _assert_one_line_error(_run(["calibrate", tmp_path / "nope.jpg", *BOARD]), "nope.jpg",
                           "no such file")


def test_photo_without_board(tmp_path):
    p = tmp_path / "forest.png"
    rng = np.random.default_rng(0)
    cv2.imwrite(str(p), cv2.GaussianBlur(rng.integers(0, 255, (480, 640), np.uint8), (0, 0), 2))
    _assert_one_line_error(_run(["calibrate", p, *BOARD, "-o", tmp_path / "c.yaml"]),
                           "found in 0 of 1 images", "need at least 3", "not found in: forest.png")


def test_board_in_fewer_than_three_views(tmp_path, boards):
    p = tmp_path / "blank.png"
    cv2.imwrite(str(p), np.full((480, 640), 128, np.uint8))
    err = _assert_one_line_error(
        _run(["calibrate", boards[0], boards[1], p, *BOARD, "-o", tmp_path / "c.yaml"]),
        "found in 2 of 3 images", "need at least 3")
    assert "found in: board0.png, board1.png" in err and "not found in: blank.png" in err


def test_one_pixel_image(tmp_path):
    p = tmp_path / "dot.png"
    cv2.imwrite(str(p), np.zeros((1, 1, 3), np.uint8))
    _assert_one_line_error(_run(["calibrate", p, *BOARD]), "dot.png", "1x1", "too small")


def test_mixed_sizes(tmp_path, boards):
    p = tmp_path / "big.png"
    cv2.imwrite(str(p), _board_image(size=(800, 600)))
    _assert_one_line_error(_run(["calibrate", *boards, p, *BOARD, "-o", tmp_path / "c.yaml"]),
                           "mixed sizes", "big.png (800x600)", "640x480")


def test_three_boards_succeed(tmp_path, boards):
    """The synthetic boards used above are fine on their own (the errors come from the bad file)."""
    r = _run(["calibrate", *boards, *BOARD, "-o", tmp_path / "c.yaml", "--json"])
    assert r.exit_code == 0, r.stderr
    assert (tmp_path / "c.yaml").is_file()


def _cam_text():
    from monodbh.calib.camera_io import camera_to_opencv_yaml

    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    return camera_to_opencv_yaml(Camera(K, np.zeros(5), (640, 480)))


@pytest.mark.parametrize("edit, words", [
    (lambda t: t.replace("image_height: 480\n", ""), ["missing key 'image_height'"]),
    (lambda t: t.replace("distortion_coefficients", "dist_coeffs"),
     ["missing key 'distortion_coefficients'"]),
    (lambda t: re.sub(r"camera_matrix: !!opencv-matrix\n(   .*\n)+?(?=distortion)",
                      "camera_matrix: !!opencv-matrix\n   rows: 2\n   cols: 3\n   dt: d\n"
                      "   data: [ 500., 0., 319.5, 0., 500., 239.5 ]\n", t),
     ["must be 3x3, got 2x3"]),
    (lambda t: "this: is: not yaml: [", ["not a valid YAML"]),
])
def test_bad_camera_file(tmp_path, edit, words):
    text = edit(_cam_text())
    cam = tmp_path / "cam.yaml"
    cam.write_text(text)
    photo = tmp_path / "ground.png"
    cv2.imwrite(str(photo), _board_image())
    _assert_one_line_error(_run(["calibrate-pose", photo, "--calib", cam, *BOARD]),
                           "cam.yaml", *words)


def test_calibrate_pose_bad_inputs(tmp_path):
    cam = tmp_path / "cam.yaml"
    cam.write_text(_cam_text())
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((480, 640), 128, np.uint8))
    _assert_one_line_error(_run(["calibrate-pose", blank, "--calib", cam, *BOARD]),
                           "blank.png", "not found")
    square = tmp_path / "square.png"
    cv2.imwrite(str(square), np.full((500, 500), 128, np.uint8))
    _assert_one_line_error(_run(["calibrate-pose", square, "--calib", cam, *BOARD]), "crop")
    _assert_one_line_error(_run(["calibrate-pose", blank, "--calib", tmp_path / "none.yaml",
                                 *BOARD]), "none.yaml", "no such file")


def test_usage_errors_exit_2(tmp_path, boards):
    r = _run(["calibrate", *boards, "--board", "nine-by-six", "--square", "0.025"])
    assert r.exit_code == 2 and "Traceback" not in r.stderr
    r = _run(["calibrate", *boards, "--board", "7x5", "--square", "0.04", "--charuco",
              "--marker", "0.05"])
    assert r.exit_code == 2 and "marker" in r.stderr
    r = _run(["calibrate", *boards])
    assert r.exit_code == 2


def test_real_entry_point_prints_no_traceback(tmp_path):
    """The installed ``dbh`` script (not only CliRunner) gives the one-line error."""
    p = tmp_path / "empty.jpg"
    p.write_bytes(b"")
    r = subprocess.run([sys.executable, "-c", "from monodbh.cli.main import main; main()",
                        "calibrate", str(p), *BOARD], capture_output=True, text=True, timeout=120)
    assert r.returncode == 1
    assert r.stderr.strip().splitlines() == [f"error: {p}: file is empty"]
