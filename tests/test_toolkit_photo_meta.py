"""toolkit.photo_meta: EXIF time, GPS, heading and size of phone-like photos; garbage never raises."""
import struct

import numpy as np
import pytest
from PIL import Image
from PIL.TiffImagePlugin import IFDRational

from geo_photos import exif_for, write_photo
from monodbh.toolkit.photo_meta import PhotoMeta, dms_to_deg, exif_datetime, read_photo_meta, tag_of
from monodbh.toolkit import photo_meta

EMPTY_GEO = dict(taken_at=None, lat_deg=None, lon_deg=None, alt_m=None, accuracy_m=None, heading_deg=None,
                 heading_ref=None)


@pytest.mark.parametrize("lat,lon", [(48.8566, 2.3522), (-33.8688, 151.2093), (40.7128, -74.006),
                                     (-54.8019, -68.303), (69.6492, 18.9553), (0.0, 0.0)])
def test_gps_hemispheres(tmp_path, lat, lon):
    p = write_photo(tmp_path / "a.jpg", exif=exif_for(lat=lat, lon=lon))
    m = read_photo_meta(str(p))
    assert m.lat_deg == pytest.approx(lat, abs=1e-8) and m.lon_deg == pytest.approx(lon, abs=1e-8)


def test_phone_photo_all_fields(tmp_path):
    ex = exif_for(lat=-33.8688, lon=151.2093, alt=-12.5, accuracy=4.7, heading=271.25, heading_ref="M",
                  taken="2026:05:14 10:32:07", offset="+10:00", orientation=6)
    p = write_photo(tmp_path / "IMG_0412.jpg", size=(64, 48), exif=ex)
    m = read_photo_meta(str(p))
    assert m == PhotoMeta(taken_at="2026-05-14T10:32:07+10:00", lat_deg=pytest.approx(-33.8688),
                          lon_deg=pytest.approx(151.2093), alt_m=-12.5, accuracy_m=4.7, heading_deg=271.25,
                          heading_ref="M", width=48, height=64)  # orientation 6: portrait


def test_png_and_no_offset(tmp_path):
    p = write_photo(tmp_path / "a.png", exif=exif_for(lat=10.5, lon=-20.25, heading=360.0, taken="2026:01:02 03:04:05"))
    m = read_photo_meta(str(p))
    assert (m.lat_deg, m.lon_deg, m.heading_deg, m.heading_ref) == (10.5, -20.25, 0.0, "T")
    assert m.taken_at == "2026-01-02T03:04:05" and (m.width, m.height) == (64, 48)


@pytest.mark.parametrize("suffix", [".jpg", ".png", ".tif", ".webp", ".bmp"])
def test_no_exif_all_empty(tmp_path, suffix):
    p = write_photo(tmp_path / f"plain{suffix}")
    m = read_photo_meta(str(p))
    assert {k: getattr(m, k) for k in EMPTY_GEO} == EMPTY_GEO
    assert (m.width, m.height) == (64, 48)


@pytest.mark.parametrize("what", ["missing", "folder", "text", "empty", "truncated"])
def test_not_a_photo_all_empty(tmp_path, what):
    p = tmp_path / "x.jpg"
    if what == "folder":
        p.mkdir()
    elif what == "text":
        p.write_text("not a photo")
    elif what == "empty":
        p.write_bytes(b"")
    elif what == "truncated":
        write_photo(p, exif=exif_for(lat=1.0, lon=2.0))
        p.write_bytes(p.read_bytes()[:40])
    assert read_photo_meta(str(p)) == PhotoMeta()


def test_garbage_values_written_to_file(tmp_path):
    """Zero denominators (NaN), out-of-range numbers, bad refs, bad dates: those values None."""
    ex = Image.Exif()
    g = ex.get_ifd(0x8825)
    g.update({1: "X", 2: (IFDRational(48, 1), IFDRational(0, 1), IFDRational(0, 1)), 3: "E",
              4: (IFDRational(1, 0), IFDRational(0, 1), IFDRational(0, 1)), 6: IFDRational(1, 0),
              16: "Q", 17: IFDRational(4000, 1), 31: IFDRational(1, 0)})
    sub = ex.get_ifd(0x8769)
    sub.update({0x9003: "2026:13:45 99:00:00", 0x9011: "bogus"})
    p = write_photo(tmp_path / "g.jpg", exif=ex)
    m = read_photo_meta(str(p))
    assert {k: getattr(m, k) for k in EMPTY_GEO} == EMPTY_GEO
    assert (m.width, m.height) == (64, 48)


def test_lat_out_of_range_and_good_date(tmp_path):
    ex = exif_for(lat=10.0, lon=170.0, taken="2026:05:14 10:32:07", offset="+99:00")
    ex.get_ifd(0x8825)[2] = (IFDRational(95, 1), IFDRational(0, 1), IFDRational(0, 1))
    m = read_photo_meta(str(write_photo(tmp_path / "g.jpg", exif=ex)))
    assert m.lat_deg is None and m.lon_deg is None      # both or neither
    assert m.taken_at == "2026-05-14T10:32:07"           # a bad offset is dropped, the time kept


def _tiff_exif_blob() -> bytes:
    """EXIF whose GPS tags have the wrong types: latitude as text, longitude as one LONG, heading as text."""
    def entry(tag, typ, count, value: bytes):
        return struct.pack(">HHI", tag, typ, count) + value.ljust(4, b"\x00")
    gps_off = 8 + 2 + 12 + 4
    ifd0 = struct.pack(">H", 1) + entry(0x8825, 4, 1, struct.pack(">I", gps_off)) + b"\x00" * 4
    gps = (struct.pack(">H", 5) + entry(1, 2, 2, b"N\x00") + entry(2, 2, 4, b"abc\x00") + entry(3, 2, 2, b"E\x00")
           + entry(4, 4, 1, struct.pack(">I", 10)) + entry(17, 2, 4, b"eas\x00") + b"\x00" * 4)
    return b"Exif\x00\x00" + b"MM\x00\x2a" + struct.pack(">I", 8) + ifd0 + gps


def test_wrong_types_in_file(tmp_path):
    p = tmp_path / "w.jpg"
    Image.fromarray(np.full((48, 64, 3), 90, np.uint8)).save(p, exif=_tiff_exif_blob())
    m = read_photo_meta(str(p))
    assert {k: getattr(m, k) for k in EMPTY_GEO} == EMPTY_GEO


@pytest.mark.parametrize("blob", [b"Exif\x00\x00MM\x00\x2a\xff\xff\xff\xff", b"Exif\x00\x00" + b"\xff" * 50,
                                  b"Exif\x00\x00II*\x00\x08\x00\x00\x00\xff\xff" + b"\x01" * 30])
def test_corrupt_exif_blob(tmp_path, blob):
    p = tmp_path / "c.jpg"
    Image.fromarray(np.full((48, 64, 3), 90, np.uint8)).save(p, exif=blob)
    m = read_photo_meta(str(p))
    assert {k: getattr(m, k) for k in EMPTY_GEO} == EMPTY_GEO


class _Boom:
    def __float__(self):
        raise ZeroDivisionError("boom")

    def __eq__(self, other):
        raise RuntimeError("no comparing")

    __hash__ = object.__hash__


class _FakeImage:
    format = "JPEG"
    size = (64, 48)

    def __init__(self, exif):
        self._exif = exif

    def getexif(self):
        return self._exif


@pytest.mark.parametrize("gps", [
    {1: None, 2: None, 3: 5, 4: [1, 2, 3]},
    {1: "N", 2: (_Boom(), 1, 2), 3: "E", 4: ((1, 2), (3, 4)), 17: _Boom(), 16: _Boom()},
    {1: "N", 2: "48 30 36", 3: "E", 4: (1, 2, 3, 4), 5: "below", 6: "high", 31: float("inf")},
    {1: b"\xff\xfe", 2: (-1, 0, 0), 3: ["E"], 4: (True, 0, 0), 5: b"", 6: 10, 17: -3},
])
def test_garbage_python_values_never_raise(gps):
    ex = Image.Exif()
    ex[0x0112] = _Boom()
    ex.get_ifd(0x8825).update(gps)
    ex.get_ifd(0x8769).update({0x9003: _Boom(), 0x9011: 7})
    m = photo_meta._meta_of(_FakeImage(ex))
    assert m.lat_deg is None and m.lon_deg is None and m.heading_deg is None and m.taken_at is None


def test_alt_ref_forms():
    assert photo_meta._altitude({5: 1, 6: 3.5}) == -3.5
    assert photo_meta._altitude({5: b"\x00", 6: 3.5}) == 3.5
    assert photo_meta._altitude({6: 3.5}) == 3.5
    assert photo_meta._altitude({5: 2, 6: 3.5}) is None


def test_dms_and_datetime():
    assert dms_to_deg((48, 30, 36)) == pytest.approx(48.51)
    assert dms_to_deg((IFDRational(4851, 100),)) == pytest.approx(48.51)
    assert dms_to_deg(()) is None and dms_to_deg((1, -2, 0)) is None and dms_to_deg("48") is None
    assert exif_datetime(b"2026:05:14 10:32:07\x00", b"-03:30") == "2026-05-14T10:32:07-03:30"
    with pytest.raises(ValueError):
        exif_datetime("    :  :     :  :  ")     # the reader wraps this in its never-raise guard


@pytest.mark.parametrize("photo,pattern,tag", [
    ("plot3/T0412_north.jpg", None, "T0412_north"),
    ("plot3/T0412_north.jpg", r"T(\d+)", "0412"),
    ("plot3/T0412_north.jpg", r"T\d+", "T0412"),
    ("plot3/IMG_1.jpg", r"T(\d+)", "IMG_1"),         # no match: the stem
    ("plot3/IMG_1.jpg", r"(X)?IMG", "IMG"),          # group 1 did not take part: the whole match
    ("plot3/IMG_1.jpg", r"\d*", "IMG_1"),            # an empty match: the stem
    ("a.b/tree.7.jpeg", r"tree\.(\d+)", "7"),
    (".hidden", None, ".hidden"),
])
def test_tag_of(photo, pattern, tag):
    assert tag_of(photo, pattern) == tag
