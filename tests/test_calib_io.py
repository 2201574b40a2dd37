"""cam.yaml: OpenCV calibration-sample FileStorage YAML and ROS camera_info, both ways."""
import cv2
import numpy as np
import pytest

from monodbh.calib import (CalibrationInfo, Camera, CameraFileError, CameraPose, load_camera,
                           save_camera)
from monodbh.calib.camera_io import camera_to_opencv_yaml

K = np.array([[1234.5678901234, 0, 640.123456789], [0, 1230.0000001, 479.5], [0, 0, 1]])
DIST = np.array([-0.2123456789, 0.0456, 1.5e-05, -0.00123, 0.0])


def _camera(pose=True):
    info = CalibrationInfo(calibration_time="Mon Jan  6 10:00:00 2025", nframes=3,
                           board_width=9, board_height=6, square_size=0.025, flags=0,
                           avg_reprojection_error=0.2345,
                           per_view_reprojection_errors=[0.1, 0.25, 0.3],
                           extrinsic_parameters=np.arange(18.0).reshape(3, 6) / 7,
                           std_deviations_intrinsics=np.linspace(0, 1, 18))
    p = CameraPose.from_angles(1.52, -12.5, 0.75) if pose else None
    return Camera(K, DIST, (1280, 960), pose=p, info=info)


def test_opencv_yaml_round_trip_with_filestorage(tmp_path):
    cam = _camera()
    path = tmp_path / "cam.yaml"
    save_camera(cam, path)
    text = path.read_text()
    assert text.startswith("%YAML:1.0\n---\n")
    assert "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n" in text
    # Our loader: identical.
    back = load_camera(path)
    assert back == cam
    assert back.pose.allclose(cam.pose, atol=0)
    # OpenCV's own reader: identical numbers.
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.isOpened()
    assert np.array_equal(fs.getNode("camera_matrix").mat(), cam.K)
    assert np.array_equal(fs.getNode("distortion_coefficients").mat().ravel(), cam.dist)
    assert fs.getNode("image_width").real() == 1280 and fs.getNode("image_height").real() == 960
    assert fs.getNode("board_width").real() == 9 and fs.getNode("nframes").real() == 3
    assert fs.getNode("square_size").real() == 0.025
    assert fs.getNode("avg_reprojection_error").real() == 0.2345
    pv = fs.getNode("per_view_reprojection_errors").mat()
    assert pv.dtype == np.float32 and np.array_equal(pv.ravel(), cam.info.per_view_reprojection_errors)
    assert np.array_equal(fs.getNode("extrinsic_parameters").mat(), cam.info.extrinsic_parameters)
    assert fs.getNode("calibration_time").string() == cam.info.calibration_time
    assert np.array_equal(fs.getNode("R_world_from_camera").mat(), cam.pose.R_world_from_camera)
    assert np.array_equal(fs.getNode("t_world_from_camera").mat().ravel(),
                          cam.pose.t_world_from_camera)
    assert fs.getNode("camera_height_m").real() == cam.pose.height_m
    fs.release()
    # Writing again gives the same bytes.
    assert camera_to_opencv_yaml(back) == text


def test_reads_opencv5_yaml_1_2(tmp_path):
    """OpenCV 5's FileStorage writes %YAML 1.2 with %.17g numbers; we read it."""
    path = tmp_path / "cv5.yml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 1280)
    fs.write("image_height", 960)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", DIST.reshape(-1, 1))
    fs.write("calibration_time", "now")
    fs.release()
    assert path.read_text().startswith("%YAML 1.2")
    cam = load_camera(path)
    assert np.array_equal(cam.K, K) and np.array_equal(cam.dist, DIST) and cam.pose is None


def test_reproduces_opencv_sample_file(shared_data, tmp_path):
    """left_intrinsics.yml (written by OpenCV's calibration sample) is rewritten byte for byte."""
    ref = shared_data / "opencv_chessboard" / "reference" / "left_intrinsics.yml"
    if not ref.is_file():
        pytest.skip(f"{ref} not found")
    cam = load_camera(ref)
    assert cam.fx == pytest.approx(535.9157339616320) and cam.image_size == (640, 480)
    assert cam.info.nframes == 13 and cam.info.flags == 2 and cam.info.aspect_ratio == 1.0
    text = camera_to_opencv_yaml(cam)
    # The reference file has no calibration_time line; everything else must match exactly.
    ours = [ln for ln in text.splitlines() if not ln.startswith("calibration_time")]
    assert ours == ref.read_text().splitlines()


def test_ros_round_trip_and_same_numbers(tmp_path):
    cam = _camera()
    save_camera(cam, tmp_path / "ros.yaml", format="ros")
    text = (tmp_path / "ros.yaml").read_text()
    assert "distortion_model: plumb_bob" in text and "projection_matrix:" in text
    assert "!!opencv-matrix" not in text
    ros = load_camera(tmp_path / "ros.yaml")
    assert np.array_equal(ros.K, cam.K) and np.array_equal(ros.dist, cam.dist)
    assert ros.image_size == cam.image_size and ros.pose.allclose(cam.pose, atol=1e-15)
    # A hand-written camera_info (as ROS camera_calibration writes it) with the same numbers.
    hand = tmp_path / "hand.yaml"
    hand.write_text(
        "image_width: 1280\nimage_height: 960\ncamera_name: narrow_stereo\n"
        "camera_matrix:\n  rows: 3\n  cols: 3\n"
        f"  data: [{float(K[0, 0])!r}, 0, {float(K[0, 2])!r}, 0, {float(K[1, 1])!r}, "
        f"{float(K[1, 2])!r}, 0, 0, 1]\n"
        "distortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n  cols: 5\n"
        "  data: [" + ", ".join(repr(float(d)) for d in DIST) + "]\n"
        "rectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n"
        "projection_matrix:\n  rows: 3\n  cols: 4\n  data: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0]\n")
    h = load_camera(hand)
    assert np.array_equal(h.K, load_camera(tmp_path / "ros.yaml").K) and h.name == "narrow_stereo"
    assert np.array_equal(h.dist, cam.dist) and h.pose is None


def test_rational_model_ros(tmp_path):
    cam = Camera(K, np.r_[DIST, 0.01, 0.02, 0.03], (1280, 960))
    save_camera(cam, tmp_path / "r.yaml", format="ros")
    assert "rational_polynomial" in (tmp_path / "r.yaml").read_text()
    assert np.array_equal(load_camera(tmp_path / "r.yaml").dist, cam.dist)
    with pytest.raises(CameraFileError, match="cannot be written"):
        save_camera(Camera(K, np.zeros(12), (1280, 960)), tmp_path / "x.yaml", format="ros")


GOOD = camera_to_opencv_yaml(Camera(K, DIST, (1280, 960)))


@pytest.mark.parametrize("text, match", [
    (GOOD.replace("image_width: 1280\n", ""), "missing key 'image_width'"),
    (GOOD.replace("camera_matrix", "camera_matrx"), "missing key 'camera_matrix'"),
    (GOOD.replace("   rows: 3\n   cols: 3", "   rows: 2\n   cols: 3", 1), "says 2x3 but has 9"),
    (GOOD.replace("distortion_coefficients: !!opencv-matrix\n   rows: 5",
                  "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   x: 5"),
     "distortion_coefficients"),
    ("image_width: 10\nimage_height: 10\ncamera_matrix:\n  rows: 2\n  cols: 2\n"
     "  data: [1, 0, 0, 1]\n", "must be 3x3, got 2x2"),
    ("a: [1, 2\n", "not a valid YAML"),
    ("- 1\n- 2\n", "not a camera file"),
    ("", "empty"),
    (GOOD.replace("image_width: 1280", "image_width: wide"), "must be an integer"),
    (GOOD + "R_world_from_camera: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
            "   data: [ 1., 0., 0., 0., 1., 0., 0., 0., 1. ]\n", "t_world_from_camera"),
])
def test_bad_files_give_one_line_errors(tmp_path, text, match):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(CameraFileError) as ei:
        load_camera(p)
    msg = str(ei.value)
    assert match in msg and str(p) in msg and "\n" not in msg, msg


def test_missing_file_and_binary(tmp_path):
    with pytest.raises(CameraFileError, match="no such file"):
        load_camera(tmp_path / "nope.yaml")
    (tmp_path / "bin.yaml").write_bytes(b"\xff\xd8\xff\x00\x81")
    with pytest.raises(CameraFileError, match="not a text file"):
        load_camera(tmp_path / "bin.yaml")
    with pytest.raises(CameraFileError, match="cannot write"):
        save_camera(Camera(K, DIST, (1280, 960)), tmp_path / "no" / "dir" / "cam.yaml")
