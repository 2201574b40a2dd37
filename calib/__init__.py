"""Camera calibration: camera model, cam.yaml I/O, checkerboard calibration, pose, photo loading.

Lives here: everything about the camera. May be imported by ``monodbh.toolkit`` and
``monodbh.cli``; imports nothing else from monodbh. OpenCV is imported lazily, inside the
functions that need it.

Public API
----------
Camera, CameraPose, CalibrationInfo
    Pinhole + OpenCV distortion model for one image size, optional pose over level ground;
    ``Camera.for_image`` adapts it to a photo (rescale, 90 degree turns; crops refused).
load_camera, save_camera
    cam.yaml in OpenCV calibration-sample FileStorage YAML (default) or ROS camera_info.
load_photo, read_image_size
    EXIF-upright 8-bit RGB photo loading for the whole toolkit.
Board, detect_board, calibrate, CalibrationResult, estimate_ground_pose
    Chessboard/ChArUco calibration and the ground pose from a board photo.
MonodbhError, PhotoError, CalibrationError, CameraFileError
    User-facing errors (one-line messages).
"""
from .board import Board, Detection, detect_board, parse_board_size
from .calibrate import CalibrationResult, ViewResult, calibrate, calibrate_views, detect_views
from .camera import CalibrationInfo, Camera, CameraPose
from .camera_io import load_camera, save_camera
from .coverage import CoverageScore, coverage_scores, view_parameters
from .errors import CalibrationError, CameraFileError, MonodbhError, PhotoError
from .photo import load_photo, read_image_size
from .pose import GroundPoseResult, estimate_ground_pose, pose_from_board

__all__ = [
    # camera model and files
    "Camera", "CameraPose", "CalibrationInfo", "load_camera", "save_camera",
    # photos
    "load_photo", "read_image_size",
    # boards and calibration
    "Board", "Detection", "detect_board", "parse_board_size",
    "calibrate", "detect_views", "calibrate_views", "CalibrationResult", "ViewResult",
    "CoverageScore", "coverage_scores", "view_parameters",
    # ground pose
    "estimate_ground_pose", "pose_from_board", "GroundPoseResult",
    # errors
    "MonodbhError", "PhotoError", "CalibrationError", "CameraFileError",
]
