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

import functools
import math
import os
import reprlib
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

# Limits of a plausible camera file, checked by load_camera (why these values:
# docs/decisions/camera-file-limits.md).
#: largest camera file read, bytes (a cam.yaml is 1-30 KB); refused before parsing, as
#: pure-Python YAML parsing takes ~8 s per MB
MAX_FILE_BYTES = 256_000
#: deepest YAML nesting (a camera file nests 3 levels: key, matrix, data list)
MAX_NESTING = 20
#: longest text value (camera_name, calibration_time, distortion_model)
MAX_TEXT_CHARS = 256
#: most rows or columns of one matrix (extrinsic_parameters has one row per view)
MAX_MATRIX_SIDE = 100_000
#: image width and height, pixels (a thumbnail to the largest JPEG/TIFF side)
IMAGE_SIDE_RANGE_PX = (16, 65535)
#: most pixels of the calibrated image (a 200 Mpx phone sensor, with room)
MAX_IMAGE_PIXELS = 300_000_000
#: horizontal and vertical field of view, degrees (phone tele ~15 to ultra-wide ~120)
FOV_RANGE_DEG = (2.0, 170.0)
#: fx / fy (square pixels give 1; anamorphic lenses 1.33 to 2)
FOCAL_RATIO_RANGE = (1.0 / 3.0, 3.0)
#: largest |skew| K[0, 1] as a fraction of fx (OpenCV calibrates with zero skew)
MAX_SKEW_RATIO = 0.1
#: the lens model must reach the image's farthest corner within this angle off axis, degrees
MAX_RAY_ANGLE_DEG = 85.0
#: directions and angle steps along which the distortion is checked to be monotonic
DIST_CHECK_DIRECTIONS = 16
DIST_CHECK_STEPS = 512
#: camera_height_m (and t_world_from_camera's z), metres: above the ground, below a tall crown
CAMERA_HEIGHT_RANGE_M = (0.01, 100.0)
#: pitch_deg and roll_deg, degrees (the ranges CameraPose's angles come back in)
PITCH_RANGE_DEG = (-90.0, 90.0)
ROLL_RANGE_DEG = (-180.0, 180.0)
_MAX_QUOTE_CHARS = 40  # a value quoted in an error message is cut to this length


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


class _Refused(Exception):
    """A camera file refused while parsing (message without the path)."""


def _short(value: Any) -> str:
    """A bounded one-line ``repr`` of ``value`` for error messages (never the whole value)."""
    r = reprlib.Repr()
    r.maxlevel, r.maxdict, r.maxlist, r.maxtuple, r.maxset = 2, 3, 4, 4, 4
    r.maxstring, r.maxlong, r.maxother = 30, 20, 30
    try:
        text = r.repr(value)
    except Exception:  # noqa: BLE001 - e.g. an int too long to print
        text = f"<{type(value).__name__}>"
    return _cut(text, _MAX_QUOTE_CHARS)


def _cut(text: str, n: int) -> str:
    """``text`` on one line, at most ``n`` characters (``...`` marks a cut)."""
    text = " ".join(str(text).split())
    return text if len(text) <= n else text[:n - 3] + "..."


@functools.lru_cache(maxsize=1)
def _yaml_loader():
    """SafeLoader that reads ``!!opencv-matrix`` and refuses anchors, aliases and deep nesting."""
    import yaml

    class Loader(yaml.SafeLoader):
        _depth = 0

        def compose_node(self, parent, index):
            event = self.peek_event()
            if isinstance(event, yaml.AliasEvent) or getattr(event, "anchor", None) is not None:
                raise _Refused(f"YAML aliases are not allowed in camera files "
                               f"(line {event.start_mark.line + 1})")
            if self._depth >= MAX_NESTING:
                raise _Refused(f"YAML nested deeper than {MAX_NESTING} levels "
                               f"(line {event.start_mark.line + 1})")
            self._depth += 1
            try:
                return super().compose_node(parent, index)
            finally:
                self._depth -= 1

    def matrix(loader, node):
        return _OpenCVMatrix(loader.construct_mapping(node, deep=True))

    for tag in ("tag:yaml.org,2002:opencv-matrix", "!opencv-matrix"):
        Loader.add_constructor(tag, matrix)
    return Loader


def _parse(text: str, p: Path) -> dict:
    """The top-level mapping of camera file text (a one-line :class:`CameraFileError` for
    invalid YAML, anchors/aliases, nesting deeper than :data:`MAX_NESTING`)."""
    import yaml

    lines = text.splitlines()
    # OpenCV's "%YAML:1.0" is not a valid directive; OpenCV 5 writes "%YAML 1.2".
    while lines and (not lines[0].strip() or lines[0].lstrip().startswith("%YAML")):
        lines.pop(0)
    try:
        data = yaml.load("\n".join(lines), Loader=_yaml_loader())  # noqa: S506 - SafeLoader subclass
    except _Refused as exc:
        raise CameraFileError(f"{p}: {exc}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        problem = _cut(getattr(exc, "problem", None) or "invalid YAML", 80)
        raise CameraFileError(f"{p}: not a valid YAML camera file ({problem}{where})") from None
    except RecursionError:
        raise CameraFileError(f"{p}: not a valid YAML camera file (nested too deeply)") from None
    except (ValueError, OverflowError, TypeError, IndexError, KeyError, AttributeError) as exc:
        # PyYAML's constructors raise these for e.g. a bad date, a 5000-digit int, "!!float"
        # with no value, "!!timestamp abc"
        raise CameraFileError(f"{p}: not a valid YAML camera file (a value cannot be read: "
                              f"{_cut(exc, 60)})") from None
    if not isinstance(data, dict):
        raise CameraFileError(f"{p}: not a camera file (expected a YAML mapping of keys)")
    return data


def _number(v: Any) -> float:
    """``v`` as a float (a YAML number, or text OpenCV wrote such as ``1e-05``); ValueError or
    OverflowError otherwise (booleans, containers, long text)."""
    if isinstance(v, bool) or not isinstance(v, (int, float, str)):
        raise ValueError
    if isinstance(v, str) and len(v) > 40:
        raise ValueError
    return float(v)


def _integer(v: Any) -> int:
    """``v`` as an int (an integer, or an integral finite float); ValueError otherwise."""
    if isinstance(v, int) and not isinstance(v, bool):
        return v
    f = _number(v)
    if not math.isfinite(f) or f != int(f):
        raise ValueError
    return int(f)


def _matrix_count(node: dict, key: str, k: str, p: Path) -> int:
    try:
        n = _integer(node[k])
    except (ValueError, OverflowError):
        raise CameraFileError(f"{p}: matrix '{key}' has non-numeric rows, cols or data "
                              f"({k}: {_short(node[k])})") from None
    if not 0 <= n <= MAX_MATRIX_SIDE:
        raise CameraFileError(f"{p}: matrix '{key}' has {k}: {_short(n)} (0 to "
                              f"{MAX_MATRIX_SIDE} accepted)")
    return n


def _matrix(data: dict, key: str, p: Path, required: bool = True) -> Optional[np.ndarray]:
    """Matrix ``key`` from either an ``!!opencv-matrix`` or a ROS ``{rows, cols, data}``: finite
    numbers of its type ``dt``, as float64."""
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
    rows, cols = _matrix_count(node, key, "rows", p), _matrix_count(node, key, "cols", p)
    values = node["data"]
    if not isinstance(values, (list, tuple)):
        values = [values]
    dt_text = node.get("dt", "d")
    dt = _DT.get(dt_text.strip()) if isinstance(dt_text, str) else None
    if dt is None:
        raise CameraFileError(f"{p}: matrix '{key}' has unsupported type dt: {_short(dt_text)}")
    try:
        arr = np.array([_number(v) for v in values], dtype=np.float64)
    except (ValueError, OverflowError):
        raise CameraFileError(f"{p}: matrix '{key}' has non-numeric rows, cols or data") from None
    if arr.size != rows * cols:
        raise CameraFileError(f"{p}: matrix '{key}' says {rows}x{cols} but has {arr.size} values")
    if not np.all(np.isfinite(arr)):
        raise CameraFileError(f"{p}: matrix '{key}' contains NaN or infinity")
    if dt is np.float64:
        return arr.reshape(rows, cols)
    if np.issubdtype(dt, np.integer):
        info = np.iinfo(dt)
        if np.any(arr != np.round(arr)) or np.any(arr < info.min) or np.any(arr > info.max):
            raise CameraFileError(f"{p}: matrix '{key}' holds values that are not of its type "
                                  f"dt: {dt_text.strip()}")
    elif np.any(np.abs(arr) > np.finfo(np.float32).max):
        raise CameraFileError(f"{p}: matrix '{key}' holds values too large for dt: f")
    return arr.astype(dt).astype(np.float64).reshape(rows, cols)


def _scalar(data: dict, key: str, p: Path, kind: type, required: bool = False) -> Any:
    """Scalar ``key``: an int, a finite float or a short text (``kind``); None when absent."""
    if key not in data or data[key] is None:
        if required:
            raise CameraFileError(f"{p}: missing key '{key}'")
        return None
    v = data[key]
    if kind is str:
        return _text(v, key, p)
    try:
        out = _integer(v) if kind is int else _number(v)
    except (ValueError, OverflowError):
        raise CameraFileError(f"{p}: '{key}' must be {'an integer' if kind is int else 'a number'}, "
                              f"got {_short(v)}") from None
    if kind is float and not math.isfinite(out):
        raise CameraFileError(f"{p}: '{key}' must be a finite number, got {_short(v)}")
    return out


def _text(v: Any, key: str, p: Path) -> str:
    """A text field (a YAML scalar, at most :data:`MAX_TEXT_CHARS` characters); never turns a
    list or mapping into text."""
    if isinstance(v, (list, tuple, dict, set, bytes, bytearray)):
        raise CameraFileError(f"{p}: '{key}' must be text, got a {type(v).__name__}")
    if isinstance(v, int) and not isinstance(v, bool) and v.bit_length() > 4 * MAX_TEXT_CHARS:
        raise CameraFileError(f"{p}: '{key}' is longer than {MAX_TEXT_CHARS} characters")
    s = str(v)
    if len(s) > MAX_TEXT_CHARS:
        raise CameraFileError(f"{p}: '{key}' is longer than {MAX_TEXT_CHARS} characters")
    return s


def _in_range(v: float, lo: float, hi: float, key: str, p: Path, unit: str) -> None:
    if not lo <= v <= hi:
        raise CameraFileError(f"{p}: '{key}' must be between {lo:g} and {hi:g} {unit}, "
                              f"got {_short(v)}")


def _read_pose(data: dict, p: Path) -> Optional[CameraPose]:
    if not any(k in data for k in _POSE_KEYS):
        return None
    R = _matrix(data, "R_world_from_camera", p, required=False)
    t = _matrix(data, "t_world_from_camera", p, required=False)
    angles_needed = R is None and t is None
    angles = {}
    for key, (lo, hi), unit in (("camera_height_m", CAMERA_HEIGHT_RANGE_M, "m"),
                                ("pitch_deg", PITCH_RANGE_DEG, "degrees"),
                                ("roll_deg", ROLL_RANGE_DEG, "degrees")):
        v = _scalar(data, key, p, float, required=angles_needed)
        if v is not None:
            _in_range(v, lo, hi, key, p, unit)
        angles[key] = v
    try:
        if angles_needed:
            return CameraPose.from_angles(angles["camera_height_m"], angles["pitch_deg"],
                                          angles["roll_deg"])
        if R is None or t is None:
            raise CameraFileError(f"{p}: pose needs both 'R_world_from_camera' and "
                                  f"'t_world_from_camera'")
        if R.shape != (3, 3):
            raise CameraFileError(f"{p}: 'R_world_from_camera' must be 3x3, got "
                                  f"{R.shape[0]}x{R.shape[1]}")
        if t.size != 3:
            raise CameraFileError(f"{p}: 't_world_from_camera' must have 3 values, got {t.size}")
        lo, hi = CAMERA_HEIGHT_RANGE_M
        if not lo <= t.flat[2] <= hi:
            raise CameraFileError(f"{p}: 't_world_from_camera' puts the camera {_short(t.flat[2])} "
                                  f"m above the ground ({lo:g} to {hi:g} m accepted)")
        return CameraPose(R, t.reshape(3))
    except ValueError as exc:
        raise CameraFileError(f"{p}: invalid camera pose ({exc})") from None


def _check_image_size(w: int, h: int, p: Path) -> None:
    """Each side within :data:`IMAGE_SIDE_RANGE_PX`, the area within :data:`MAX_IMAGE_PIXELS`."""
    lo, hi = IMAGE_SIDE_RANGE_PX
    for key, v in (("image_width", w), ("image_height", h)):
        if not lo <= v <= hi:
            raise CameraFileError(f"{p}: '{key}' must be between {lo} and {hi} pixels, "
                                  f"got {_short(v)}")
    if w * h > MAX_IMAGE_PIXELS:
        raise CameraFileError(f"{p}: image size {w}x{h} is over {MAX_IMAGE_PIXELS / 1e6:g} "
                              f"megapixels")


def _check_camera_matrix(K: np.ndarray, w: int, h: int, p: Path) -> None:
    """Fields of view in :data:`FOV_RANGE_DEG`, fx/fy in :data:`FOCAL_RATIO_RANGE`, the
    principal point inside the image, skew under :data:`MAX_SKEW_RATIO` of fx."""
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    lo, hi = FOV_RANGE_DEG
    for side, n, f, name in (("horizontal", w, fx, "fx"), ("vertical", h, fy, "fy")):
        fov = math.degrees(2.0 * math.atan(n / 2.0 / f))
        if not lo <= fov <= hi:
            raise CameraFileError(f"{p}: 'camera_matrix' gives a {side} field of view of {fov:.3g} "
                                  f"degrees ({name} = {f:.6g} px for {n} px; {lo:g} to {hi:g} "
                                  f"degrees accepted)")
    rlo, rhi = FOCAL_RATIO_RANGE
    if not rlo <= fx / fy <= rhi:
        raise CameraFileError(f"{p}: 'camera_matrix' has fx/fy = {fx / fy:.3g} ({rlo:.3g} to "
                              f"{rhi:.3g} accepted)")
    for name, c, n in (("cx", cx, w), ("cy", cy, h)):
        if not -0.5 <= c <= n - 0.5:
            raise CameraFileError(f"{p}: 'camera_matrix' puts the principal point outside the "
                                  f"image ({name} = {c:.6g}, image {w}x{h})")
    if abs(skew) > MAX_SKEW_RATIO * fx:
        raise CameraFileError(f"{p}: 'camera_matrix' skew {skew:.6g} is over "
                              f"{MAX_SKEW_RATIO:g} fx")


def _check_distortion(K: np.ndarray, dist: np.ndarray, w: int, h: int, p: Path) -> None:
    """The distorted radius grows strictly with the ray's angle until it reaches the image's
    farthest corner, along :data:`DIST_CHECK_DIRECTIONS` directions and within
    :data:`MAX_RAY_ANGLE_DEG` off axis (``cv2.projectPoints`` with all coefficients)."""
    import cv2

    c = np.array([K[0, 2], K[1, 2]])
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    r_corner = float(np.hypot(*(corners - c).T).max())
    theta = np.linspace(0.0, math.radians(MAX_RAY_ANGLE_DEG), DIST_CHECK_STEPS + 1)
    rn = np.tan(theta)                                          # undistorted normalized radius
    phi = np.linspace(0.0, 2.0 * math.pi, DIST_CHECK_DIRECTIONS, endpoint=False)
    xy = rn[None, :, None] * np.stack([np.cos(phi), np.sin(phi)], -1)[:, None, :]
    obj = np.concatenate([xy, np.ones(xy.shape[:2] + (1,))], -1).reshape(-1, 1, 3)
    with np.errstate(all="ignore"):
        uv, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), K, dist)
        r = np.hypot(*(uv.reshape(len(phi), len(rn), 2) - c).transpose(2, 0, 1))
    for row in r:
        reached = np.flatnonzero(row >= r_corner)
        end = reached[0] if reached.size else len(row) - 1
        seg = row[:end + 1]
        bad = np.flatnonzero(~(np.diff(seg) > 0))               # NaN counts as a fold
        if bad.size:
            raise CameraFileError(f"{p}: distortion_coefficients fold back inside the image (the "
                                  f"lens model is not monotonic beyond r = {rn[bad[0]]:.3g})")
        if not reached.size:
            raise CameraFileError(f"{p}: camera_matrix and distortion_coefficients do not reach "
                                  f"the image corner within {MAX_RAY_ANGLE_DEG:g} degrees off "
                                  f"axis")


def _camera_from_data(data: dict, p: Path) -> Camera:
    if "camera_matrix" not in data:
        raise CameraFileError(f"{p}: missing key 'camera_matrix' (not a camera calibration file?)")
    cm = data["camera_matrix"]
    is_ros = not isinstance(cm, _OpenCVMatrix)
    w = _scalar(data, "image_width", p, int, required=True)
    h = _scalar(data, "image_height", p, int, required=True)
    if w <= 0 or h <= 0:
        raise CameraFileError(f"{p}: image size must be positive, got {_short(w)}x{_short(h)}")
    K = _matrix(data, "camera_matrix", p)
    if K.shape != (3, 3):
        raise CameraFileError(f"{p}: 'camera_matrix' must be 3x3, got {K.shape[0]}x{K.shape[1]}")
    if is_ros:
        model = _text(data.get("distortion_model", "plumb_bob"), "distortion_model", p).strip()
        if model not in ("plumb_bob", "rational_polynomial"):
            raise CameraFileError(f"{p}: distortion_model {_short(model)} is not supported "
                                  f"(plumb_bob or rational_polynomial)")
    dist = _matrix(data, "distortion_coefficients", p, required=not is_ros)
    if dist is None:
        dist = np.zeros((1, 5))
    if min(dist.shape) > 1 or dist.size not in DIST_LENGTHS:
        raise CameraFileError(f"{p}: 'distortion_coefficients' must be a 1xN or Nx1 vector with "
                              f"N in {DIST_LENGTHS}, got {dist.shape[0]}x{dist.shape[1]}")
    if not (K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0, 0, 1]) and K[1, 0] == 0
            and K[2, 0] == 0):
        raise CameraFileError(f"{p}: 'camera_matrix' is not [[fx, 0, cx], [0, fy, cy], "
                              f"[0, 0, 1]] with positive focal lengths")
    K[2] = (0.0, 0.0, 1.0)
    _check_image_size(w, h, p)
    _check_camera_matrix(K, w, h, p)
    _check_distortion(K, dist.reshape(-1), w, h, p)
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
        Missing/unreadable file, a file over :data:`MAX_FILE_BYTES`, invalid YAML, YAML anchors
        or aliases, nesting deeper than :data:`MAX_NESTING`, missing keys, wrong matrix shapes
        or values, NaN or infinity, or an implausible camera (image size, field of view,
        principal point, skew, a distortion that folds back inside the image, camera pose out
        of range: the limits at the top of this module,
        ``docs/decisions/camera-file-limits.md``).
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a str or os.PathLike, got {type(path).__name__}")
    p = Path(path)
    return _camera_from_data(_parse(_read_camera_text(p), p), p)


def _read_camera_text(p: Path) -> str:
    """The text of camera file ``p``; a one-line :class:`CameraFileError` when it is missing, a
    folder, empty, over :data:`MAX_FILE_BYTES`, not UTF-8 text or OpenCV XML."""
    if not p.exists():
        raise CameraFileError(f"{p}: no such file")
    if p.is_dir():
        raise CameraFileError(f"{p}: is a directory, not a camera file")
    try:
        with open(p, "rb") as f:
            raw = f.read(MAX_FILE_BYTES + 1)     # bounded: also for /dev/zero or a growing file
    except OSError as exc:
        raise CameraFileError(f"{p}: cannot read ({exc.strerror or exc})") from None
    if len(raw) > MAX_FILE_BYTES:
        raise CameraFileError(f"{p}: file is over {MAX_FILE_BYTES // 1000} KB; not a camera file "
                              f"(a cam.yaml is a few KB)")
    if not raw.strip():
        raise CameraFileError(f"{p}: file is empty")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise CameraFileError(f"{p}: not a text file (expected YAML)") from None
    if text.lstrip().startswith("<?xml") or text.lstrip().startswith("<opencv_storage"):
        raise CameraFileError(f"{p}: OpenCV XML camera files are not supported; use YAML")
    return text
