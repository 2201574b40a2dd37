"""Hostile inputs for ``tests/test_hostile_cli.py``, generated at test time.

Every function here writes one bad (or merely odd) file into a folder and returns its path:
photos (truncated, corrupt, bombs, tiny, animated, rotated, ...) and camera files (alias bombs,
deep nesting, implausible lenses, ...). They are built from the bundled example photo and camera
(``toolkit/examples``), so no data set is needed.
"""
from __future__ import annotations

import io
import os
import shutil
import struct
import zlib
from pathlib import Path

import numpy as np
from PIL import Image

REPO = Path(__file__).resolve().parents[1]
EXAMPLE_JPG = REPO / "toolkit" / "examples" / "example.jpg"
EXAMPLE_CAM = REPO / "toolkit" / "examples" / "cam.yaml"

__all__ = ["EXAMPLE_JPG", "EXAMPLE_CAM", "good_photo", "good_camera", "PHOTOS", "CAMERAS"]


def good_photo(d: Path, name: str | bytes = "tree.jpg") -> Path:
    """A copy of the bundled example photo (1280x960, measurable)."""
    p = Path(d) / (name if isinstance(name, str) else os.fsdecode(name))
    shutil.copyfile(EXAMPLE_JPG, p)
    return p


def good_camera(d: Path, name: str = "cam.yaml") -> Path:
    p = Path(d) / name
    shutil.copyfile(EXAMPLE_CAM, p)
    return p


def _example_image() -> Image.Image:
    with Image.open(EXAMPLE_JPG) as im:
        return im.convert("RGB")


# -- photos ------------------------------------------------------------------------------------
def _jpeg_bytes() -> bytes:
    return EXAMPLE_JPG.read_bytes()


def _sos_end(data: bytes) -> int:
    """Offset of the first byte of entropy-coded data after the JPEG's start-of-scan header."""
    i = 2
    while i < len(data):
        marker = data[i + 1]
        seg = (data[i + 2] << 8) | data[i + 3]
        if marker == 0xDA:
            return i + 2 + seg
        i += 2 + seg
    raise ValueError("no scan")


def photo_empty(d):
    p = d / "empty.jpg"
    p.write_bytes(b"")
    return p


def photo_text(d):
    p = d / "notes.jpg"
    p.write_text("tree 12, DBH 31 cm\n")
    return p


def photo_html(d):
    p = d / "page.jpg"
    p.write_text("<!DOCTYPE html><html><body>404 Not Found</body></html>\n")
    return p


def photo_junk(d):
    p = d / "junk.jpg"
    p.write_bytes(np.random.default_rng(1).integers(0, 256, 50_000, dtype=np.uint8).tobytes())
    return p


def photo_truncated_jpeg(d):
    p = d / "truncated.jpg"
    data = _jpeg_bytes()
    p.write_bytes(data[: len(data) // 2])
    return p


def photo_truncated_png(d):
    p = d / "truncated.png"
    buf = io.BytesIO()
    _example_image().save(buf, "PNG")
    p.write_bytes(buf.getvalue()[: buf.tell() // 2])
    return p


def photo_corrupt_middle(d):
    """Random bytes written over the middle of the entropy-coded data (no 0xFF: the marker
    structure stays valid, only the pixels are garbage)."""
    p = d / "corrupt_middle.jpg"
    data = bytearray(_jpeg_bytes())
    start = _sos_end(bytes(data))
    mid = start + (len(data) - start) // 2
    junk = np.random.default_rng(2).integers(0, 255, 4000, dtype=np.uint8)
    data[mid:mid + 4000] = junk.tobytes()
    p.write_bytes(bytes(data))
    return p


def photo_header_108mp(d):
    """A 16x16 JPEG whose frame header claims 12000x9000 px."""
    p = d / "claims_108mp.jpg"
    buf = io.BytesIO()
    Image.new("RGB", (16, 16), (90, 60, 40)).save(buf, "JPEG", quality=90)
    data = bytearray(buf.getvalue())
    i = 2
    while i < len(data):
        marker = data[i + 1]
        seg = (data[i + 2] << 8) | data[i + 3]
        if marker in (0xC0, 0xC1, 0xC2):
            data[i + 5:i + 9] = struct.pack(">HH", 9000, 12000)   # height, width
            break
        i += 2 + seg
    p.write_bytes(bytes(data))
    return p


def _png_chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def photo_png_bomb(d):
    """A 30000x30000 gray PNG of zeros: a few hundred KB on disk, 900 Mpx decoded."""
    p = d / "bomb.png"
    w = h = 30000
    row = b"\x00" + b"\x00" * w
    comp = zlib.compressobj(9)
    body = b"".join(comp.compress(row) for _ in range(h)) + comp.flush()
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", body)
                  + _png_chunk(b"IEND", b""))
    return p


def photo_png_bad_crc(d):
    p = d / "bad_crc.png"
    buf = io.BytesIO()
    _example_image().resize((320, 240)).save(buf, "PNG")
    data = bytearray(buf.getvalue())
    idat = data.find(b"IDAT")
    length = struct.unpack(">I", data[idat - 4:idat])[0]
    data[idat + 4 + length] ^= 0xFF                                     # first CRC byte of IDAT
    p.write_bytes(bytes(data))
    return p


def photo_tiff_huge_header(d):
    """A TIFF whose header claims 60000x60000 px with a few bytes of strip data."""
    p = d / "huge.tif"
    buf = io.BytesIO()
    Image.new("L", (8, 8), 128).save(buf, "TIFF")
    data = bytearray(buf.getvalue())
    # rewrite ImageWidth (256) and ImageLength (257) entries of the first IFD
    ifd = struct.unpack("<I", data[4:8])[0]
    n = struct.unpack("<H", data[ifd:ifd + 2])[0]
    for k in range(n):
        e = ifd + 2 + 12 * k
        tag, typ = struct.unpack("<HH", data[e:e + 4])
        if tag in (256, 257):
            if typ == 3:
                data[e + 8:e + 10] = struct.pack("<H", 60000)
            else:
                data[e + 8:e + 12] = struct.pack("<I", 60000)
    p.write_bytes(bytes(data))
    return p


def photo_1px(d):
    p = d / "one_pixel.png"
    Image.new("RGB", (1, 1), (200, 30, 30)).save(p)
    return p


def photo_10px(d):
    p = d / "ten_pixels.jpg"
    Image.new("RGB", (10, 10), (120, 90, 60)).save(p)
    return p


def photo_thin_strip(d):
    p = d / "strip.png"
    _example_image().resize((1280, 3)).save(p)
    return p


def photo_animated_gif(d):
    p = d / "animated.gif"
    im = _example_image().resize((320, 240))
    frames = [im, im.transpose(Image.FLIP_LEFT_RIGHT), im.rotate(5)]
    frames[0].save(p, save_all=True, append_images=frames[1:], duration=100, loop=0)
    return p


def photo_rotated_no_exif(d):
    """The example turned on its side, with no EXIF orientation to undo it."""
    p = d / "sideways.jpg"
    _example_image().rotate(-90, expand=True).save(p, quality=92)
    return p


def photo_rotated_ccw_no_exif(d):
    """The example turned the other way (no rope is found in it)."""
    p = d / "sideways_ccw.jpg"
    _example_image().rotate(90, expand=True).save(p, quality=92)
    return p


def photo_png_renamed_jpg(d):
    """A valid PNG of the example with a .jpg name (not hostile: must be measured)."""
    p = d / "really_png.jpg"
    _example_image().save(p, "PNG")
    return p


def photo_exif_orientation_garbage(d):
    """The example with EXIF orientation 99 (no such orientation): loaded as stored."""
    p = d / "orient99.jpg"
    im = _example_image()
    exif = Image.Exif()
    exif[0x0112] = 99
    im.save(p, quality=92, exif=exif.tobytes())
    return p


def photo_cmyk(d):
    p = d / "cmyk.jpg"
    _example_image().convert("CMYK").save(p, quality=92)
    return p


def photo_other_aspect(d):
    """A 16:9 crop: the 4:3 camera file cannot be used for it."""
    p = d / "cropped.jpg"
    _example_image().crop((0, 120, 1280, 840)).save(p, quality=92)
    return p


PHOTOS = {f.__name__[len("photo_"):]: f for f in [
    photo_empty, photo_text, photo_html, photo_junk, photo_truncated_jpeg, photo_truncated_png,
    photo_corrupt_middle, photo_header_108mp, photo_png_bomb, photo_png_bad_crc,
    photo_tiff_huge_header, photo_1px, photo_10px, photo_thin_strip, photo_animated_gif,
    photo_rotated_no_exif, photo_rotated_ccw_no_exif, photo_png_renamed_jpg, photo_exif_orientation_garbage, photo_cmyk,
    photo_other_aspect]}


# -- camera files -------------------------------------------------------------------------------
def _cam_text() -> str:
    return EXAMPLE_CAM.read_text()


def _write(d: Path, name: str, text: str | bytes) -> Path:
    p = d / name
    (p.write_bytes if isinstance(text, bytes) else p.write_text)(text)
    return p


def _replace_key(text: str, key: str, value: str) -> str:
    out = []
    for line in text.splitlines():
        out.append(f"{key}: {value}" if line.startswith(f"{key}:") else line)
    return "\n".join(out) + "\n"


def _with_K(fx: float, fy: float, cx: float, cy: float) -> str:
    lines = _cam_text().splitlines()
    i = next(k for k, l in enumerate(lines) if l.startswith("camera_matrix:"))
    j = next(k for k in range(i, len(lines)) if lines[k].strip().endswith("]"))
    block = ["camera_matrix: !!opencv-matrix", "   rows: 3", "   cols: 3", "   dt: d",
             f"   data: [ {fx!r}, 0., {cx!r}, 0., {fy!r}, {cy!r}, 0., 0., 1. ]"]
    return "\n".join(lines[:i] + block + lines[j + 1:]) + "\n"


def _with_dist(values: list[float]) -> str:
    lines = _cam_text().splitlines()
    i = next(k for k, l in enumerate(lines) if l.startswith("distortion_coefficients:"))
    j = next(k for k in range(i, len(lines)) if lines[k].strip().endswith("]"))
    block = ["distortion_coefficients: !!opencv-matrix", f"   rows: {len(values)}", "   cols: 1",
             "   dt: d", "   data: [ " + ", ".join(repr(float(v)) for v in values) + " ]"]
    return "\n".join(lines[:i] + block + lines[j + 1:]) + "\n"


def _alias_bomb(depth: int = 9, width: int = 9) -> str:
    """Anchors nesting ``width`` aliases ``depth`` levels deep: ``width ** depth`` leaves."""
    lines = ['a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for k in range(1, depth):
        lines.append(f"a{k}: &a{k} [" + ",".join([f"*a{k - 1}"] * width) + "]")
    return "\n".join(lines)


def cam_missing(d):
    return d / "no_such_cam.yaml"


def cam_empty(d):
    return _write(d, "empty.yaml", "")


def cam_binary(d):
    return _write(d, "binary.yaml", bytes(range(256)) * 4)


def cam_xml(d):
    return _write(d, "cam.xml.yaml", '<?xml version="1.0"?>\n<opencv_storage></opencv_storage>\n')


def cam_not_mapping(d):
    return _write(d, "list.yaml", "- 1\n- 2\n")


def cam_no_matrix(d):
    return _write(d, "no_matrix.yaml", "image_width: 1280\nimage_height: 960\n")


def cam_width_inf(d):
    return _write(d, "width_inf.yaml", _replace_key(_cam_text(), "image_width", ".inf"))


def cam_width_1e300(d):
    return _write(d, "width_1e300.yaml", _replace_key(_cam_text(), "image_width", "1e300"))


def cam_width_huge_int(d):
    return _write(d, "width_huge.yaml", _replace_key(_cam_text(), "image_width", "9" * 40))


def cam_size_absurd(d):
    t = _replace_key(_replace_key(_cam_text(), "image_width", "1280000"), "image_height", "960000")
    return _write(d, "size_absurd.yaml", t)


def cam_deep_nesting(d):
    return _write(d, "deep.yaml", _cam_text() + "camera_name: " + "[" * 20000 + "]" * 20000 + "\n")


def cam_alias_bomb_name(d):
    return _write(d, "bomb_name.yaml", _cam_text() + _alias_bomb() + "\ncamera_name: *a8\n")


def cam_alias_bomb_time(d):
    t = _replace_key(_cam_text(), "calibration_time", "*a8")
    return _write(d, "bomb_time.yaml", _alias_bomb() + "\n" + t.split("---\n", 1)[1])


def cam_alias_bomb_dt(d):
    t = _cam_text().replace("   dt: d", "   dt: *a8", 1)
    return _write(d, "bomb_dt.yaml", _alias_bomb() + "\n" + t.split("---\n", 1)[1])


def cam_alias_bomb_ros_model(d):
    ros = ("image_width: 1280\nimage_height: 960\ncamera_name: cam\n"
           "camera_matrix:\n  rows: 3\n  cols: 3\n  data: [997.4, 0, 649.7, 0, 997.4, 470.7, 0, 0, 1]\n"
           "distortion_model: *a8\n"
           "distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [0, 0, 0, 0, 0]\n")
    return _write(d, "bomb_ros.yaml", _alias_bomb() + "\n" + ros)


def cam_alias_bomb_width(d):
    """The bomb where a number is expected: the error message must not quote it whole."""
    t = _replace_key(_cam_text(), "image_width", "*a8")
    return _write(d, "bomb_width.yaml", _alias_bomb() + "\n" + t.split("---\n", 1)[1])


def cam_nan_focal(d):
    return _write(d, "nan_focal.yaml", _with_K(float("nan"), 997.0, 650.0, 470.0).replace("nan", ".nan"))


def cam_tiny_fov(d):
    """fx = 5e6 px on a 1280 px wide image: a 0.015 degree field of view."""
    return _write(d, "tiny_fov.yaml", _with_K(5e6, 5e6, 650.0, 470.0))


def cam_huge_fov(d):
    """fx = 2 px: 179.7 degrees, beyond any pinhole lens."""
    return _write(d, "huge_fov.yaml", _with_K(2.0, 2.0, 650.0, 470.0))


def cam_principal_point_outside(d):
    return _write(d, "pp_outside.yaml", _with_K(997.0, 997.0, 250000.0, -90000.0))


def cam_aspect_absurd(d):
    return _write(d, "fx_fy.yaml", _with_K(997.0, 40.0, 650.0, 470.0))


def cam_negative_focal(d):
    return _write(d, "neg_focal.yaml", _with_K(-997.0, 997.0, 650.0, 470.0))


def cam_distortion_folds(d):
    """k1 = -3: the radial map folds back well inside the image."""
    return _write(d, "folds.yaml", _with_dist([-3.0, 0.0, 0.0, 0.0, 0.0]))


def cam_distortion_nan(d):
    return _write(d, "dist_nan.yaml", _with_dist([0.1, 0.0, 0.0, 0.0, 0.0]).replace("0.1", ".nan", 1))


def cam_matrix_wrong_size(d):
    t = _cam_text().replace("   rows: 3\n   cols: 3", "   rows: 2\n   cols: 3", 1)
    return _write(d, "matrix_2x3.yaml", t)


def cam_pose_nan(d):
    return _write(d, "pose_nan.yaml", _cam_text() + "camera_height_m: .nan\npitch_deg: 0.\nroll_deg: 0.\n")


def cam_pose_absurd(d):
    return _write(d, "pose_high.yaml", _cam_text() + "camera_height_m: 1.0e+06\npitch_deg: 0.\nroll_deg: 0.\n")


def cam_marker_width_absurd(d):
    return _write(d, "marker_huge.yaml", _cam_text() + "marker_width_mm: 1.0e+09\n")


def cam_marker_width_text(d):
    return _write(d, "marker_text.yaml", _cam_text() + "marker_width_mm: thick\n")


def cam_huge_file(d):
    """A valid camera followed by 8 MB of comments."""
    return _write(d, "huge.yaml", _cam_text() + ("# " + "x" * 98 + "\n") * 80_000)


def cam_directory(d):
    p = d / "cam_dir.yaml"
    p.mkdir()
    return p


CAMERAS = {f.__name__[len("cam_"):]: f for f in [
    cam_missing, cam_empty, cam_binary, cam_xml, cam_not_mapping, cam_no_matrix, cam_width_inf,
    cam_width_1e300, cam_width_huge_int, cam_size_absurd, cam_deep_nesting, cam_alias_bomb_name,
    cam_alias_bomb_time, cam_alias_bomb_dt, cam_alias_bomb_ros_model, cam_alias_bomb_width,
    cam_nan_focal, cam_tiny_fov, cam_huge_fov, cam_principal_point_outside, cam_aspect_absurd,
    cam_negative_focal, cam_distortion_folds, cam_distortion_nan, cam_matrix_wrong_size,
    cam_pose_nan, cam_pose_absurd, cam_marker_width_absurd, cam_marker_width_text, cam_huge_file,
    cam_directory]}
