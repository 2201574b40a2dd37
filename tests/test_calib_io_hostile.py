"""Hostile and implausible camera files: a one-line ``CameraFileError`` naming the file and the
key, never a traceback, never a memory blow-up (limits: docs/decisions/camera-file-limits.md)."""
import json
import math
import time
import tracemalloc
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st
from typer.testing import CliRunner

from monodbh.calib import Camera, CameraFileError, load_camera
from monodbh.calib import camera_io as cio
from monodbh.calib.marker import read_marker_width_m
from monodbh.cli.main import app

EXAMPLE = Path(__file__).resolve().parents[1] / "toolkit" / "examples" / "cam.yaml"
K9 = ("1000.", "0.", "639.5", "0.", "1000.", "479.5", "0.", "0.", "1.")
DIST5 = ("0.01", "-0.02", "0.001", "0.002", "0.003")
SETTINGS = dict(deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                      HealthCheck.too_slow])


def _mat(key, rows, cols, data, dt="d"):
    return (f"{key}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: {dt}\n"
            f"   data: [ {', '.join(str(v) for v in data)} ]\n")


def cv(width="1280", height="960", K=K9, dist=DIST5, dt="d", prefix="", extra="",
       pose=True, **scalars):
    """OpenCV FileStorage camera text; every value is raw YAML text (None omits a key)."""
    fields = {"calibration_time": '"Mon Jan  6 10:00:00 2025"', "nframes": "12",
              "square_size": "0.025", "camera_name": '"nikon"'}
    if pose:
        fields.update(camera_height_m="1.5", pitch_deg="-10.", roll_deg="1.")
    fields.update(scalars)
    out = "%YAML:1.0\n---\n" + prefix
    out += "".join(f"{k}: {v}\n" for k, v in (("image_width", width), ("image_height", height))
                   if v is not None)
    out += _mat("camera_matrix", 3, 3, K, dt) + _mat("distortion_coefficients", len(dist), 1, dist)
    out += "".join(f"{k}: {v}\n" for k, v in fields.items() if v is not None)
    return out + extra


def ros(model="plumb_bob", name="narrow_stereo", prefix=""):
    return (prefix + f"image_width: 1280\nimage_height: 960\ncamera_name: {name}\n"
            "camera_matrix:\n  rows: 3\n  cols: 3\n  data: [1000, 0, 639.5, 0, 1000, 479.5, 0, 0, 1]\n"
            f"distortion_model: {model}\n"
            "distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [0.01, -0.02, 0, 0, 0]\n")


def bomb(levels=9, width=9):
    """Billion-laughs lines defining ``*l{levels-1}`` (width**levels strings when expanded)."""
    lines = ["l0: &l0 [" + ", ".join(['"xxxxxxxxxx"'] * width) + "]"]
    lines += [f"l{i}: &l{i} [" + ", ".join([f"*l{i - 1}"] * width) + "]" for i in range(1, levels)]
    return "\n".join(lines) + "\n", f"*l{levels - 1}"


B, REF = bomb()
DEEP_LIST = "[" * 10000 + "]" * 10000
DEEP_MAP = "{a: " * 10000 + "1" + "}" * 10000
WIDE_K = ("300.", "0.", "1999.5", "0.", "300.", "1499.5", "0.", "0.", "1.")   # 4000x3000, ~140 deg

HOSTILE = [
    # 1. tracebacks before: infinities, huge numbers, deep nesting, values PyYAML cannot build
    ("inf_width", cv(width=".inf"), ["image_width", "integer"]),
    ("minus_inf_height", cv(height="-.inf"), ["image_height", "integer"]),
    ("nan_width", cv(width=".nan"), ["image_width"]),
    ("1e300_width", cv(width="1.0e+300"), ["image_width", "between"]),
    ("huge_int_width", cv(width="9" * 400), ["image_width", "between"]),
    ("5000_digit_int", cv(width="9" * 5000), ["not a valid YAML"]),
    ("deep_list", cv(extra=f"junk: {DEEP_LIST}\n"), ["nested deeper than 20"]),
    ("deep_map", cv(extra=f"junk: {DEEP_MAP}\n"), ["nested deeper than 20"]),
    ("deep_block", cv(extra="junk:\n" + "".join(" " * i + "- \n" for i in range(0, 60, 2))),
     ["nested deeper than 20"]),
    ("inf_rows", cv().replace("   rows: 3", "   rows: .inf", 1), ["camera_matrix", "rows"]),
    ("bad_date", cv(calibration_time="2026-13-45"), ["not a valid YAML"]),
    ("bad_float_tag", cv(square_size="!!float abc"), ["not a valid YAML"]),
    ("empty_float_tag", cv(square_size="!!float"), ["not a valid YAML"]),
    ("bad_timestamp_tag", cv(calibration_time="!!timestamp abc"), ["not a valid YAML"]),
    ("python_tag", cv(camera_name="!!python/object/apply:os.system [echo]"), ["not a valid YAML"]),
    # 2. memory blow-ups: aliases (billion laughs) anywhere, containers turned into text
    ("bomb_camera_name", cv(prefix=B, camera_name=REF), ["aliases are not allowed", "line"]),
    ("bomb_calibration_time", cv(prefix=B, calibration_time=REF), ["aliases are not allowed"]),
    ("bomb_dt", cv(prefix=B, dt=REF), ["aliases are not allowed"]),
    ("bomb_image_width", cv(prefix=B, width=REF), ["aliases are not allowed"]),
    ("bomb_ros_model", ros(prefix=B, model=REF), ["aliases are not allowed"]),
    ("bomb_ros_name", ros(prefix=B, name=REF), ["aliases are not allowed"]),
    ("one_alias", cv(extra="a: &x 5\nb: *x\n"), ["aliases are not allowed"]),
    ("list_camera_name", cv(camera_name="[" + ", ".join(["x"] * 1000) + "]"),
     ["camera_name", "must be text"]),
    ("dict_calibration_time", cv(calibration_time="{a: 1, b: 2}"), ["calibration_time", "text"]),
    ("list_ros_model", ros(model="[plumb_bob, x]"), ["distortion_model", "text"]),
    ("dict_dt", cv(dt="{a: 1}"), ["camera_matrix", "dt"]),
    ("long_name", cv(camera_name="x" * 5000), ["camera_name", "longer than 256"]),
    ("long_list_width", cv(width="[" + ", ".join(["12345"] * 2000) + "]"), ["image_width"]),
    ("over_size_limit", cv(extra="junk: [" + ", ".join(["1.5"] * 70000) + "]\n"), ["over 256 KB"]),
    # 3. implausible values
    ("width_8", cv(width="8"), ["image_width", "between 16 and 65535"]),
    ("height_70000", cv(height="70000"), ["image_height", "between"]),
    ("400_megapixels", cv(width="20000", height="20000",
                          K=("10000.", "0", "9999.5", "0", "10000.", "9999.5", "0", "0", "1")),
     ["megapixels"]),
    ("nan_fx", cv(K=(".nan",) + K9[1:]), ["camera_matrix", "NaN"]),
    ("inf_k1", cv(dist=(".inf",) + DIST5[1:]), ["distortion_coefficients", "NaN"]),
    ("tiny_fov", cv(K=("1.0e+7", "0", "639.5", "0", "1.0e+7", "479.5", "0", "0", "1")),
     ["camera_matrix", "horizontal field of view"]),
    ("tiny_vertical_fov", cv(K=("1000.", "0", "639.5", "0", "30000.", "479.5", "0", "0", "1")),
     ["camera_matrix", "vertical field of view"]),
    ("huge_fov", cv(K=("1.", "0", "639.5", "0", "1.", "479.5", "0", "0", "1")),
     ["camera_matrix", "horizontal field of view", "170"]),
    ("focal_ratio", cv(K=("1000.", "0", "639.5", "0", "250.", "479.5", "0", "0", "1")),
     ["camera_matrix", "fx/fy"]),
    ("cx_outside", cv(K=K9[:2] + ("1.0e+6",) + K9[3:]), ["camera_matrix", "principal point", "cx"]),
    ("cy_negative", cv(K=K9[:5] + ("-100.",) + K9[6:]), ["principal point", "cy"]),
    ("skew", cv(K=("1000.", "500.") + K9[2:]), ["camera_matrix", "skew"]),
    ("k1_minus_2_wide", cv(width="4000", height="3000", K=WIDE_K, dist=("-2.", "0", "0", "0", "0")),
     ["distortion_coefficients fold back inside the image", "r ="]),
    ("k2_minus_5", cv(dist=("0.", "-5.", "0", "0", "0")), ["fold back"]),
    ("rational_k4", cv(dist=("0", "0", "0", "0", "0", "5.", "0", "0")), ["fold back"]),
    ("corner_beyond_85deg", cv(width="4000", height="3000", K=("200.", "0", "1999.5", "0", "200.",
                                                                "1499.5", "0", "0", "1"),
                               dist=("0",) * 5), ["do not reach the image corner", "85"]),
    ("nan_square_size", cv(square_size=".nan"), ["square_size", "finite"]),
    ("inf_nframes", cv(nframes=".inf"), ["nframes", "integer"]),
    ("nan_height_m", cv(camera_height_m=".nan"), ["camera_height_m", "finite"]),
    ("negative_height_m", cv(camera_height_m="-1.5"), ["camera_height_m", "between"]),
    ("height_1km", cv(camera_height_m="1000."), ["camera_height_m", "between 0.01 and 100"]),
    ("inf_pitch", cv(pitch_deg=".inf"), ["pitch_deg", "finite"]),
    ("pitch_200", cv(pitch_deg="200."), ["pitch_deg", "between -90 and 90"]),
    ("roll_1e9", cv(roll_deg="1.0e+9"), ["roll_deg", "between"]),
    ("list_pitch", cv(pitch_deg="[1, 2, 3]"), ["pitch_deg", "must be a number"]),
    ("t_height_1e6", cv(pose=False, extra=_mat("R_world_from_camera", 3, 3, (0, 0, 1, -1, 0, 0, 0, -1, 0))
                        + _mat("t_world_from_camera", 3, 1, (0, 0, "1.0e+6"))),
     ["t_world_from_camera", "above the ground"]),
    ("bool_fx", cv(K=("true",) + K9[1:]), ["camera_matrix", "non-numeric"]),
]


def _assert_one_line(msg, path, words):
    assert "\n" not in msg and len(msg) < 300, msg
    assert str(path) in msg, msg
    for w in words:
        assert w in msg, (w, msg)


def test_builders_give_loadable_files(tmp_path):
    """The hostile cases differ from these valid files only in the broken value."""
    for i, text in enumerate((cv(), ros(), cv(width="4000", height="3000", K=WIDE_K,
                                               dist=("-0.1", "0.01", "0", "0", "0")))):
        p = tmp_path / f"ok{i}.yaml"
        p.write_text(text)
        assert isinstance(load_camera(p), Camera)


@pytest.mark.parametrize("name, text, words", HOSTILE, ids=[c[0] for c in HOSTILE])
def test_hostile_file_one_line_error(tmp_path, name, text, words):
    p = tmp_path / f"{name}.yaml"
    p.write_text(text)
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(CameraFileError) as ei:
            load_camera(p)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert time.perf_counter() - t0 < 5.0
    assert peak < 50e6, f"{peak / 1e6:.0f} MB"
    _assert_one_line(str(ei.value), p, words)


@pytest.mark.skipif(not Path("/dev/zero").exists(), reason="no /dev/zero")
def test_endless_file_is_not_read_to_the_end():
    with pytest.raises(CameraFileError, match="over 256 KB") as ei:
        load_camera("/dev/zero")
    _assert_one_line(str(ei.value), "/dev/zero", [])


def test_alias_bomb_refused_fast_without_memory(tmp_path):
    """Billion laughs (9**9 strings when expanded) in a text field: refused before expanding."""
    b, ref = bomb(levels=9, width=9)
    p = tmp_path / "bomb.yaml"
    p.write_text(cv(prefix=b, camera_name=ref))
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(CameraFileError, match="aliases are not allowed"):
            load_camera(p)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert time.perf_counter() - t0 < 1.0 and peak < 50e6


def test_marker_width_reader_still_bounded(tmp_path):
    """read_marker_width_m goes through the same parser: aliases refused, range still checked."""
    p = tmp_path / "cam.yaml"
    b, ref = bomb()
    p.write_text(cv(prefix=b, marker_width_mm=ref))
    with pytest.raises(CameraFileError, match="aliases are not allowed"):
        read_marker_width_m(p)
    p.write_text(cv(marker_width_mm=".inf"))
    with pytest.raises(CameraFileError, match="marker_width_mm"):
        read_marker_width_m(p)
    p.write_text(cv(marker_width_mm="10"))
    assert read_marker_width_m(p) == pytest.approx(0.01)


def test_shipped_example_still_loads():
    cam = load_camera(EXAMPLE)
    assert cam.image_size == (1280, 960)


# ------------------------------------------------------------------------------------------
# the command line
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name, text, word", [
    ("bomb", cv(prefix=B, camera_name=REF), "aliases are not allowed"),
    ("tiny_fov", cv(K=("1.0e+7", "0", "639.5", "0", "1.0e+7", "479.5", "0", "0", "1")),
     "field of view"),
    ("deep", cv(extra=f"junk: {DEEP_LIST}\n"), "nested deeper"),
    ("inf_width", cv(width=".inf"), "image_width"),
])
def test_measure_with_hostile_calib(tmp_path, name, text, word):
    cam = tmp_path / "bad.yaml"
    cam.write_text(text)
    photo = tmp_path / "photo.png"
    cv2.imwrite(str(photo), np.full((960, 1280, 3), 128, np.uint8))
    r = CliRunner().invoke(app, ["measure", str(photo), "--calib", str(cam)])
    assert r.exit_code == 1, (r.exit_code, r.stdout, r.stderr)
    err = r.stderr.strip()
    assert err.startswith("error: ") and len(err.splitlines()) == 1, err
    assert "Traceback" not in r.stdout + r.stderr
    assert "bad.yaml" in err and word in err, err


# ------------------------------------------------------------------------------------------
# property-based: anything in, a Camera or a CameraFileError out
# ------------------------------------------------------------------------------------------
def _load_or_error(path: Path, text=None, data=None):
    if text is not None:
        path.write_text(text, encoding="utf-8", errors="surrogatepass")
    if data is not None:
        path.write_bytes(data)
    try:
        return load_camera(path)
    except CameraFileError as exc:
        assert "\n" not in str(exc) and len(str(exc)) < 300, str(exc)
        return None


def _assert_plausible(cam: Camera) -> None:
    """The rules of the reader, checked independently on a Camera it returned."""
    w, h = cam.image_size
    lo, hi = cio.IMAGE_SIDE_RANGE_PX
    assert lo <= w <= hi and lo <= h <= hi and w * h <= cio.MAX_IMAGE_PIXELS
    assert np.all(np.isfinite(cam.K)) and np.all(np.isfinite(cam.dist))
    flo, fhi = cio.FOV_RANGE_DEG
    for n, f in ((w, cam.fx), (h, cam.fy)):
        assert flo <= math.degrees(2 * math.atan(n / 2 / f)) <= fhi
    assert cio.FOCAL_RATIO_RANGE[0] <= cam.fx / cam.fy <= cio.FOCAL_RATIO_RANGE[1]
    assert -0.5 <= cam.cx <= w - 0.5 and -0.5 <= cam.cy <= h - 0.5
    assert abs(cam.K[0, 1]) <= cio.MAX_SKEW_RATIO * cam.fx
    # along the diagonals: projected radius increases until the farthest corner
    c = np.array([cam.cx, cam.cy])
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    r_corner = np.hypot(*(corners - c).T).max()
    t = np.tan(np.linspace(0, math.radians(cio.MAX_RAY_ANGLE_DEG), 300))
    for dx, dy in ((1, 1), (-1, 1), (1, -1), (-1, -1)):
        d = np.array([dx, dy]) / math.sqrt(2)
        pts = np.c_[t[:, None] * d, np.ones(len(t))]
        r = np.hypot(*(cam.project(pts) - c).T)
        end = np.flatnonzero(r >= r_corner)
        assert end.size
        assert np.all(np.diff(r[:end[0] + 1]) > 0)
    if cam.pose is not None:
        plo, phi = cio.CAMERA_HEIGHT_RANGE_M
        assert plo <= cam.pose.height_m <= phi


YAML_TOKENS = st.sampled_from(
    ["[", "]", "{", "}", ": ", ", ", "- ", "\n", "  ", "&a ", "*a", "!!opencv-matrix", "%YAML:1.0\n",
     "---\n", "image_width", "image_height", "camera_matrix", "rows", "cols", "data", "dt", "d",
     "3", "1280", ".inf", ".nan", "1e9", "-1", "0.5", '"x"', "'", "?", "|", ">", "#", "!!float",
     "2026-13-45", "distortion_coefficients", "camera_name", "pitch_deg", "\t", "\x00"])


@settings(max_examples=150, **SETTINGS)
@given(st.text(max_size=400))
def test_any_text_gives_camera_or_error(tmp_path, text):
    cam = _load_or_error(tmp_path / "t.yaml", text=text)
    if cam is not None:
        _assert_plausible(cam)


@settings(max_examples=100, **SETTINGS)
@given(st.binary(max_size=400))
def test_any_bytes_give_camera_or_error(tmp_path, data):
    _load_or_error(tmp_path / "b.yaml", data=data)


@settings(max_examples=150, **SETTINGS)
@given(st.lists(YAML_TOKENS, max_size=60).map("".join))
def test_yamlish_token_soup_gives_camera_or_error(tmp_path, text):
    cam = _load_or_error(tmp_path / "y.yaml", text=text)
    if cam is not None:
        _assert_plausible(cam)


@settings(max_examples=100, **SETTINGS)
@given(st.integers(0, 2000), st.integers(0, 2000))
def test_cut_and_spliced_valid_files_give_camera_or_error(tmp_path, a, b):
    good = cv()
    cam = _load_or_error(tmp_path / "c.yaml", text=good[:a] + good[b:])
    if cam is not None:
        _assert_plausible(cam)


VALUES = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(allow_nan=True, allow_infinity=True).map(lambda v: f"{v:.6e}"),
    st.floats(-1e4, 1e4).map(lambda v: f"{v:.4f}"),
    st.integers(-10**30, 10**30).map(str),
    st.integers(-5, 70000).map(str),
    st.text(max_size=20).map(json.dumps),
    st.sampled_from([".nan", ".inf", "-.inf", "[1, 2]", "{a: 1}", "", "~", "true", "[]", "{}",
                     "!!binary aGVsbG8=", "0x10", "1_000", "2026-01-06", "'1e-05'"]),
    st.lists(st.integers(-3, 3), max_size=5).map(str),
)
SCALAR_KEYS = ["width", "height", "dt", "calibration_time", "nframes", "square_size",
               "camera_name", "camera_height_m", "pitch_deg", "roll_deg"]


@settings(max_examples=250, **SETTINGS)
@given(st.sampled_from(SCALAR_KEYS + ["K", "dist"]), st.integers(0, 8), VALUES)
def test_mutated_valid_file_gives_camera_or_error(tmp_path, key, index, value):
    if key in ("K", "dist"):
        data = list(K9 if key == "K" else DIST5)
        data[index % len(data)] = value
        text = cv(**{key: tuple(data)})
    else:
        text = cv(**{key: value})
    cam = _load_or_error(tmp_path / "m.yaml", text=text)
    if cam is not None:
        _assert_plausible(cam)


@settings(max_examples=100, **SETTINGS)
@given(st.floats(50, 20000), st.floats(50, 20000), st.floats(-5, 5), st.floats(-5, 5),
       st.floats(-2, 2), st.floats(-0.5, 0.5), st.floats(-0.5, 0.5))
def test_random_numeric_cameras_give_camera_or_error(tmp_path, fx, fy, k1, k2, k3, cxf, cyf):
    K = (repr(fx), "0", repr(640 * (1 + cxf)), "0", repr(fy), repr(480 * (1 + cyf)), "0", "0", "1")
    text = cv(K=K, dist=(repr(k1), repr(k2), "0", "0", repr(k3)))
    cam = _load_or_error(tmp_path / "n.yaml", text=text)
    if cam is not None:
        _assert_plausible(cam)
