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
    Chessboard/ChArUco calibration and the ground pose from a board photo (loaded on first
    use: measuring a photo never imports the calibration workflow).
MonodbhError, PhotoError, CalibrationError, CameraFileError
    User-facing errors (one-line messages).
"""
from .camera import CalibrationInfo, Camera, CameraPose
from .camera_io import load_camera, save_camera
from .errors import CalibrationError, CameraFileError, MonodbhError, PhotoError
from .photo import load_photo, read_image_size

#: names of the calibration workflow, imported on first use: measuring a photo with a camera
#: file needs the camera model, cam.yaml I/O and photo loading only
_LAZY = {
    "Board": "board", "Detection": "board", "detect_board": "board", "parse_board_size": "board",
    "CalibrationResult": "calibration", "ViewResult": "calibration", "calibrate": "calibration",
    "calibrate_views": "calibration", "detect_views": "calibration",
    "CoverageScore": "coverage", "coverage_scores": "coverage", "view_parameters": "coverage",
    "GroundPoseResult": "pose", "estimate_ground_pose": "pose", "pose_from_board": "pose",
}


def __getattr__(name: str):
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f"{__name__}.{mod}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


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
