"""cam.yaml reading and writing: OpenCV FileStorage YAML and ROS ``camera_info`` YAML.

OpenCV format (the default)
    Written byte-for-byte in the style of OpenCV's calibration sample
    (``samples/cpp/calibration.cpp``, FileStorage of OpenCV 3/4): ``%YAML:1.0`` header,
    ``!!opencv-matrix`` blocks, doubles as ``%.16e`` (integers as ``1.``), floats as ``%.8e``,
    flow sequences wrapped at 71 columns. Keys: ``calibration_time``, ``nframes``,
    ``image_width``, ``image_height``, ``board_width``, ``board_height``, ``square_size``,
    [``aspectRatio``], ``flags``, ``camera_matrix``, ``distortion_coefficients``,
    ``avg_reprojection_error``, ``per_view_reprojection_errors``, [``extrinsic_parameters``],
    and monodbh extras: [``std_deviations_intrinsics``], [``camera_name``], and the pose
    [``camera_height_m``, ``pitch_deg``, ``roll_deg``, ``R_world_from_camera``,
    ``t_world_from_camera``]. Both ``%YAML:1.0`` and ``%YAML 1.2`` (OpenCV 5) files are read.
ROS format
    ``camera_info`` YAML of ``camera_calibration``/``camera_calibration_parsers``:
    ``image_width``, ``image_height``, ``camera_name``, ``camera_matrix``,
    ``distortion_model`` (``plumb_bob`` or ``rational_polynomial``),
    ``distortion_coefficients``, ``rectification_matrix``, ``projection_matrix`` (matrices as
    ``{rows, cols, data}``) plus the same pose extras.

The format is detected on load: ``!!opencv-matrix`` entries mean OpenCV, ``{rows, cols,
data}`` mappings mean ROS.
"""
from __future__ import annotations

import math
import os
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np

from .camera import DIST_LENGTHS, CalibrationInfo, Camera, CameraPose
from .errors import CameraFileError

__all__ = ["load_camera", "save_camera", "camera_to_opencv_yaml", "camera_to_ros_yaml",
           "FORMATS"]

FORMATS = ("opencv", "ros")

_DT = {"u": np.uint8, "c": np.int8, "w": np.uint16, "s": np.int16, "i": np.int32,
       "f": np.float32, "d": np.float64}
_POSE_KEYS = ("camera_height_m", "pitch_deg", "roll_deg", "R_world_from_camera",
              "t_world_from_camera")
_WRAP = 71  # OpenCV's YAML emitter wraps flow sequences at this column


# ------------------------------------------------------------------------------------------
# writing: OpenCV FileStorage style
# ------------------------------------------------------------------------------------------
def _cv_double(v: float) -> str:
    """``cv::FileStorage`` formatting of a double (``doubleToString``)."""
    v = float(v)
    if math.isnan(v):
        return ".Nan"
    if math.isinf(v):
        return ".Inf" if v > 0 else "-.Inf"
    if abs(v) < 2**31 and v == int(v):
        return f"{int(v)}."
    return "%.16e" % v


def _cv_float(v: float) -> str:
    """``cv::FileStorage`` formatting of a float (``floatToString``)."""
    v = float(np.float32(v))
    if math.isnan(v):
        return ".Nan"
    if math.isinf(v):
        return ".Inf" if v > 0 else "-.Inf"
    if abs(v) < 2**31 and v == int(v):
        return f"{int(v)}."
    return "%.8e" % v


def _cv_matrix(key: str, m: np.ndarray, dt: str) -> list[str]:
    m = np.asarray(m)
    if m.ndim == 1:
        m = m.reshape(-1, 1)
    fmt = {"d": _cv_double, "f": _cv_float}.get(dt, lambda x: str(int(x)))
    items = [fmt(x) for x in m.ravel()]
    lines = [f"{key}: !!opencv-matrix", f"   rows: {m.shape[0]}", f"   cols: {m.shape[1]}",
             f"   dt: {dt}"]
    line, indent = "   data: [ ", 7
    for i, it in enumerate(items):
        if i:
            line += ","
            new_offset = len(line) + len(it)
            if new_offset > _WRAP and new_offset - indent > 10:
                lines.append(line)
                line = " " * indent
            else:
                line += " "
        line += it
    lines.append(line + " ]")
    return lines


def _cv_string(s: str) -> str:
    return '"' + str(s).replace("\\", "\\\\").replace('"', '\\"') + '"'


def camera_to_opencv_yaml(camera: Camera) -> str:
    """Text of ``camera`` in OpenCV's calibration-sample FileStorage YAML (see module doc)."""
    info = camera.info or CalibrationInfo()
    out = ["%YAML:1.0", "---"]
    out.append("calibration_time: " + _cv_string(info.calibration_time or time.strftime("%c")))
    if info.nframes is not None:
        out.append(f"nframes: {int(info.nframes)}")
    out.append(f"image_width: {camera.width}")
    out.append(f"image_height: {camera.height}")
    if info.board_width is not None:
        out.append(f"board_width: {int(info.board_width)}")
    if info.board_height is not None:
        out.append(f"board_height: {int(info.board_height)}")
    if info.square_size is not None:
        out.append(f"square_size: {_cv_double(info.square_size)}")
    if info.aspect_ratio is not None:
        out.append(f"aspectRatio: {_cv_double(info.aspect_ratio)}")
    out.append(f"flags: {int(info.flags)}")
    out += _cv_matrix("camera_matrix", camera.K, "d")
    out += _cv_matrix("distortion_coefficients", camera.dist.reshape(-1, 1), "d")
    if info.avg_reprojection_error is not None:
        out.append(f"avg_reprojection_error: {_cv_double(info.avg_reprojection_error)}")
    if info.per_view_reprojection_errors is not None and info.per_view_reprojection_errors.size:
        out += _cv_matrix("per_view_reprojection_errors",
                          info.per_view_reprojection_errors.reshape(-1, 1), "f")
    if info.extrinsic_parameters is not None and info.extrinsic_parameters.size:
        out += _cv_matrix("extrinsic_parameters", info.extrinsic_parameters, "d")
    if info.std_deviations_intrinsics is not None and info.std_deviations_intrinsics.size:
        out += _cv_matrix("std_deviations_intrinsics",
                          info.std_deviations_intrinsics.reshape(-1, 1), "d")
    if camera.name != "camera":
        out.append("camera_name: " + _cv_string(camera.name))
    if camera.pose is not None:
        p = camera.pose
        out.append(f"camera_height_m: {_cv_double(p.height_m)}")
        out.append(f"pitch_deg: {_cv_double(p.pitch_deg)}")
        out.append(f"roll_deg: {_cv_double(p.roll_deg)}")
        out += _cv_matrix("R_world_from_camera", p.R_world_from_camera, "d")
        out += _cv_matrix("t_world_from_camera", p.t_world_from_camera.reshape(3, 1), "d")
    return "\n".join(out) + "\n"


# ------------------------------------------------------------------------------------------
# writing: ROS camera_info
# ------------------------------------------------------------------------------------------
def _ros_num(v: float) -> str:
    v = float(v)
    if math.isnan(v):
        return ".nan"
    if math.isinf(v):
        return ".inf" if v > 0 else "-.inf"
    s = repr(v)
    if "e" in s:
        mant, exp = s.split("e")
        if "." not in mant:
            mant += ".0"
        if exp[0] not in "+-":
            exp = "+" + exp
        s = f"{mant}e{exp}"
    return s


def _ros_matrix(key: str, m: np.ndarray) -> list[str]:
    m = np.asarray(m, dtype=np.float64)
    return [f"{key}:", f"  rows: {m.shape[0]}", f"  cols: {m.shape[1]}",
            "  data: [" + ", ".join(_ros_num(x) for x in m.ravel()) + "]"]


def camera_to_ros_yaml(camera: Camera) -> str:
    """Text of ``camera`` as a ROS ``camera_info`` YAML (monocular: R = I, P from alpha = 0).

    Raises
    ------
    CameraFileError
        The distortion model (12 or 14 coefficients) has no ROS name.
    """
    import cv2

    n = camera.dist.size
    if n <= 5:
        model, dist = "plumb_bob", np.concatenate([camera.dist, np.zeros(5 - n)])
    elif n == 8:
        model, dist = "rational_polynomial", camera.dist
    else:
        raise CameraFileError(f"a {n}-coefficient distortion model cannot be written as ROS "
                              f"camera_info (only plumb_bob and rational_polynomial)")
    P = np.zeros((3, 4))
    P[:, :3], _ = cv2.getOptimalNewCameraMatrix(camera.K, camera.dist, camera.image_size, 0.0)
    out = [f"image_width: {camera.width}", f"image_height: {camera.height}",
           f"camera_name: {camera.name}"]
    out += _ros_matrix("camera_matrix", camera.K)
    out.append(f"distortion_model: {model}")
    out += _ros_matrix("distortion_coefficients", dist.reshape(1, -1))
    out += _ros_matrix("rectification_matrix", np.eye(3))
    out += _ros_matrix("projection_matrix", P)
    if camera.pose is not None:
        p = camera.pose
        out.append(f"camera_height_m: {_ros_num(p.height_m)}")
        out.append(f"pitch_deg: {_ros_num(p.pitch_deg)}")
        out.append(f"roll_deg: {_ros_num(p.roll_deg)}")
        out += _ros_matrix("R_world_from_camera", p.R_world_from_camera)
        out += _ros_matrix("t_world_from_camera", p.t_world_from_camera.reshape(3, 1))
    return "\n".join(out) + "\n"


def save_camera(camera: Camera, path: Any, format: str = "opencv") -> None:
    """Write a camera file.

    Parameters
    ----------
    camera : Camera
        The camera (with its pose and calibration info, if any).
    path : str or os.PathLike
        Output file; written atomically (temporary file, then rename).
    format : {"opencv", "ros"}
        OpenCV calibration-sample FileStorage YAML (default) or ROS ``camera_info`` YAML.

    Raises
    ------
    CameraFileError
        The file cannot be written, or the camera does not fit the format.
    """
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a Camera, got {type(camera).__name__}")
    if format not in FORMATS:
        raise ValueError(f"format must be one of {FORMATS}, got {format!r}")
    text = camera_to_opencv_yaml(camera) if format == "opencv" else camera_to_ros_yaml(camera)
    _write_text_atomic(Path(path), text)


def _write_text_atomic(p: Path, text: str) -> None:
    """Write ``text`` to ``p`` through a temporary file and a rename (a one-line
    :class:`CameraFileError` when it cannot be written)."""
    tmp = p.with_name(f".{p.name}.tmp{os.getpid()}")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, p)
    except OSError as exc:
        try:
            tmp.unlink()
        except OSError:
            pass
        raise CameraFileError(f"{p}: cannot write ({exc.strerror or exc})") from None


# ------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------
class _OpenCVMatrix(dict):
    """Marker for a parsed ``!!opencv-matrix`` mapping."""


def _yaml_loader():
    import yaml

    class Loader(yaml.SafeLoader):
        pass

    def matrix(loader, node):
        return _OpenCVMatrix(loader.construct_mapping(node, deep=True))

    for tag in ("tag:yaml.org,2002:opencv-matrix", "!opencv-matrix"):
        Loader.add_constructor(tag, matrix)
    return Loader


def _parse(text: str, p: Path) -> dict:
    import yaml

    lines = text.splitlines()
    # OpenCV's "%YAML:1.0" is not a valid directive; OpenCV 5 writes "%YAML 1.2".
    while lines and (not lines[0].strip() or lines[0].lstrip().startswith("%YAML")):
        lines.pop(0)
    try:
        data = yaml.load("\n".join(lines), Loader=_yaml_loader())  # noqa: S506 - SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or "invalid YAML"
        raise CameraFileError(f"{p}: not a valid YAML camera file ({problem}{where})") from None
    if not isinstance(data, dict):
        raise CameraFileError(f"{p}: not a camera file (expected a YAML mapping of keys)")
    return data


def _matrix(data: dict, key: str, p: Path, required: bool = True) -> Optional[np.ndarray]:
    """Matrix ``key`` from either an ``!!opencv-matrix`` or a ROS ``{rows, cols, data}``."""
    node = data.get(key)
    if node is None:
        if required:
            raise CameraFileError(f"{p}: missing key '{key}'")
        return None
    if not isinstance(node, dict):
        raise CameraFileError(f"{p}: '{key}' must be a matrix with rows, cols and data")
    for k in ("rows", "cols", "data"):
        if k not in node:
            raise CameraFileError(f"{p}: matrix '{key}' has no '{k}'")
    try:
        rows, cols = int(node["rows"]), int(node["cols"])
        values = node["data"]
        if not isinstance(values, (list, tuple)):
            values = [values]
        dt = _DT.get(str(node.get("dt", "d")).strip(), None)
        if dt is None:
            raise CameraFileError(f"{p}: matrix '{key}' has unsupported type dt: {node.get('dt')}")
        arr = np.array([float(v) for v in values], dtype=np.float64)
    except CameraFileError:
        raise
    except (TypeError, ValueError):
        raise CameraFileError(f"{p}: matrix '{key}' has non-numeric rows, cols or data") from None
    if rows < 0 or cols < 0 or arr.size != rows * cols:
        raise CameraFileError(f"{p}: matrix '{key}' says {rows}x{cols} but has {arr.size} values")
    return arr.astype(dt).astype(np.float64).reshape(rows, cols) if dt is not np.float64 \
        else arr.reshape(rows, cols)


def _scalar(data: dict, key: str, p: Path, kind: type, required: bool = False) -> Any:
    if key not in data or data[key] is None:
        if required:
            raise CameraFileError(f"{p}: missing key '{key}'")
        return None
    v = data[key]
    try:
        if kind is int:
            f = float(v)
            if f != int(f):
                raise ValueError
            return int(f)
        if kind is float:
            return float(v)
        return str(v)
    except (TypeError, ValueError):
        raise CameraFileError(f"{p}: '{key}' must be {'an integer' if kind is int else 'a number'}, "
                              f"got {v!r}") from None


def _read_pose(data: dict, p: Path) -> Optional[CameraPose]:
    if not any(k in data for k in _POSE_KEYS):
        return None
    R = _matrix(data, "R_world_from_camera", p, required=False)
    t = _matrix(data, "t_world_from_camera", p, required=False)
    try:
        if R is not None or t is not None:
            if R is None or t is None:
                raise CameraFileError(f"{p}: pose needs both 'R_world_from_camera' and "
                                      f"'t_world_from_camera'")
            if R.shape != (3, 3):
                raise CameraFileError(f"{p}: 'R_world_from_camera' must be 3x3, got "
                                      f"{R.shape[0]}x{R.shape[1]}")
            if t.size != 3:
                raise CameraFileError(f"{p}: 't_world_from_camera' must have 3 values, got {t.size}")
            return CameraPose(R, t.reshape(3))
        h = _scalar(data, "camera_height_m", p, float, required=True)
        pitch = _scalar(data, "pitch_deg", p, float, required=True)
        roll = _scalar(data, "roll_deg", p, float, required=True)
        return CameraPose.from_angles(h, pitch, roll)
    except ValueError as exc:
        raise CameraFileError(f"{p}: invalid camera pose ({exc})") from None


def _camera_from_data(data: dict, p: Path) -> Camera:
    if "camera_matrix" not in data:
        raise CameraFileError(f"{p}: missing key 'camera_matrix' (not a camera calibration file?)")
    cm = data["camera_matrix"]
    is_ros = not isinstance(cm, _OpenCVMatrix)
    w = _scalar(data, "image_width", p, int, required=True)
    h = _scalar(data, "image_height", p, int, required=True)
    if w <= 0 or h <= 0:
        raise CameraFileError(f"{p}: image size must be positive, got {w}x{h}")
    K = _matrix(data, "camera_matrix", p)
    if K.shape != (3, 3):
        raise CameraFileError(f"{p}: 'camera_matrix' must be 3x3, got {K.shape[0]}x{K.shape[1]}")
    if is_ros:
        model = str(data.get("distortion_model", "plumb_bob")).strip()
        if model not in ("plumb_bob", "rational_polynomial"):
            raise CameraFileError(f"{p}: distortion_model '{model}' is not supported "
                                  f"(plumb_bob or rational_polynomial)")
    dist = _matrix(data, "distortion_coefficients", p, required=not is_ros)
    if dist is None:
        dist = np.zeros((1, 5))
    if min(dist.shape) > 1 or dist.size not in DIST_LENGTHS:
        raise CameraFileError(f"{p}: 'distortion_coefficients' must be a 1xN or Nx1 vector with "
                              f"N in {DIST_LENGTHS}, got {dist.shape[0]}x{dist.shape[1]}")
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist))):
        raise CameraFileError(f"{p}: camera matrix or distortion contains NaN or infinity")
    if not (K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0, 0, 1]) and K[1, 0] == 0
            and K[2, 0] == 0):
        raise CameraFileError(f"{p}: 'camera_matrix' is not [[fx, 0, cx], [0, fy, cy], "
                              f"[0, 0, 1]] with positive focal lengths")
    K[2] = (0.0, 0.0, 1.0)
    pose = _read_pose(data, p)
    name = _scalar(data, "camera_name", p, str) or "camera"
    info = None
    if not is_ros:
        pv = _matrix(data, "per_view_reprojection_errors", p, required=False)
        ex = _matrix(data, "extrinsic_parameters", p, required=False)
        sd = _matrix(data, "std_deviations_intrinsics", p, required=False)
        if ex is not None and ex.size and ex.shape[1] != 6:
            raise CameraFileError(f"{p}: 'extrinsic_parameters' must be Nx6, got "
                                  f"{ex.shape[0]}x{ex.shape[1]}")
        info = CalibrationInfo(
            calibration_time=_scalar(data, "calibration_time", p, str),
            nframes=_scalar(data, "nframes", p, int),
            board_width=_scalar(data, "board_width", p, int),
            board_height=_scalar(data, "board_height", p, int),
            square_size=_scalar(data, "square_size", p, float),
            aspect_ratio=_scalar(data, "aspectRatio", p, float),
            flags=_scalar(data, "flags", p, int) or 0,
            avg_reprojection_error=_scalar(data, "avg_reprojection_error", p, float),
            per_view_reprojection_errors=pv,
            extrinsic_parameters=ex,
            std_deviations_intrinsics=sd,
        )
    try:
        return Camera(K, dist.reshape(-1), (w, h), pose=pose, name=name, info=info)
    except ValueError as exc:  # pragma: no cover - checked above
        raise CameraFileError(f"{p}: {exc}") from None


def load_camera(path: Any) -> Camera:
    """Read a camera file, OpenCV FileStorage YAML or ROS ``camera_info`` (autodetected).

    Parameters
    ----------
    path : str or os.PathLike
        cam.yaml written by ``dbh calibrate``, OpenCV's calibration sample (``%YAML:1.0`` or
        OpenCV 5's ``%YAML 1.2``) or ROS ``camera_calibration``.

    Returns
    -------
    Camera
        With ``pose`` when the file holds one, and ``info`` for OpenCV files.

    Raises
    ------
    CameraFileError
        Missing/unreadable file, invalid YAML, missing keys, wrong matrix shapes or values.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a str or os.PathLike, got {type(path).__name__}")
    p = Path(path)
    return _camera_from_data(_parse(_read_camera_text(p), p), p)


def _read_camera_text(p: Path) -> str:
    """The text of camera file ``p``; a one-line :class:`CameraFileError` when it is missing, a
    folder, empty, not UTF-8 text or OpenCV XML."""
    if not p.exists():
        raise CameraFileError(f"{p}: no such file")
    if p.is_dir():
        raise CameraFileError(f"{p}: is a directory, not a camera file")
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise CameraFileError(f"{p}: cannot read ({exc.strerror or exc})") from None
    if not raw.strip():
        raise CameraFileError(f"{p}: file is empty")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise CameraFileError(f"{p}: not a text file (expected YAML)") from None
    if text.lstrip().startswith("<?xml") or text.lstrip().startswith("<opencv_storage"):
        raise CameraFileError(f"{p}: OpenCV XML camera files are not supported; use YAML")
    return text
