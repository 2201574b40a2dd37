"""What a photo's EXIF says about where, when and which way it was taken (Pillow only).

:func:`read_photo_meta` reads the capture time (``DateTimeOriginal`` with ``OffsetTimeOriginal``),
the camera's GPS position (latitude, longitude, altitude, horizontal accuracy) and the compass
heading of the optical axis (``GPSImgDirection`` with its ``T``/``M`` reference), plus the photo's
size after the EXIF orientation (as :func:`monodbh.calib.load_photo` returns it), into a
:class:`PhotoMeta`. It never raises: a photo without EXIF, or with garbage in a tag, gives
``None`` for what cannot be read, one tag at a time. Only the header is read (no pixels).

:func:`tag_of` is a photo's field tag: the file stem, or a part of the file name picked by a
regular expression (``dbh measure --tag-from``).

Imported by :mod:`monodbh.toolkit.batch`; imports the standard library and Pillow.
"""
from __future__ import annotations

import math
import re
import warnings
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any, Optional

__all__ = ["PhotoMeta", "read_photo_meta", "tag_of", "dms_to_deg", "exif_datetime",
           "GPS_IFD", "EXIF_IFD"]

#: EXIF pointers to the GPS and Exif sub-IFDs (``Image.Exif.get_ifd``)
GPS_IFD = 0x8825
EXIF_IFD = 0x8769

_ORIENTATION = 0x0112
_SWAPPING_ORIENTATIONS = (5, 6, 7, 8)
_DATETIME_ORIGINAL = 0x9003
_OFFSET_TIME_ORIGINAL = 0x9011
# GPS IFD tags
_LAT_REF, _LAT, _LON_REF, _LON, _ALT_REF, _ALT = 1, 2, 3, 4, 5, 6
_IMG_DIR_REF, _IMG_DIR, _H_POS_ERROR = 16, 17, 31

_OFFSET_RE = re.compile(r"[+-](?:[01]\d|2[0-3]):[0-5]\d")


@dataclass(frozen=True)
class PhotoMeta:
    """A photo's EXIF facts for the field record; every attribute may be None (not in the photo).

    Attributes
    ----------
    taken_at : str or None
        ``DateTimeOriginal`` as ISO 8601 text (``2026-05-14T10:32:07``), with the UTC offset of
        ``OffsetTimeOriginal`` appended when present (``2026-05-14T10:32:07+02:00``).
    lat_deg, lon_deg : float or None
        Camera position, WGS 84 degrees (north and east positive); both or neither.
    alt_m : float or None
        Altitude, metres above sea level (negative below).
    accuracy_m : float or None
        ``GPSHPositioningError``: horizontal position error, metres.
    heading_deg : float or None
        ``GPSImgDirection``: compass bearing of the optical axis, degrees in [0, 360).
    heading_ref : {"T", "M"} or None
        ``GPSImgDirectionRef``: true or magnetic north.
    width, height : int or None
        Photo size in pixels after the EXIF orientation (as ``load_photo`` returns it).
    """
    taken_at: Optional[str] = None
    lat_deg: Optional[float] = None
    lon_deg: Optional[float] = None
    alt_m: Optional[float] = None
    accuracy_m: Optional[float] = None
    heading_deg: Optional[float] = None
    heading_ref: Optional[str] = None
    width: Optional[int] = None
    height: Optional[int] = None


def tag_of(photo: str, pattern: Optional[str | re.Pattern] = None) -> str:
    """The field tag of ``photo``: its file stem, or what ``pattern`` finds in its file name.

    Parameters
    ----------
    photo : str
        The photo's path.
    pattern : str or re.Pattern, optional
        Searched (``re.search``) in the file name with its extension; the tag is its first group
        when that group matched, else the whole match. No match, or an empty one: the stem.

    Examples
    --------
    >>> tag_of("plot3/T0412_north.jpg", r"T(\\d+)")
    '0412'
    >>> tag_of("plot3/IMG_1.jpg", r"T(\\d+)")
    'IMG_1'
    """
    name = Path(str(photo)).name
    stem = Path(name).stem or name
    if pattern is None:
        return stem
    m = re.search(pattern, name)
    if m is None:
        return stem
    tag = m.group(1) if m.re.groups and m.group(1) is not None else m.group(0)
    return tag or stem


def read_photo_meta(path: str) -> PhotoMeta:
    """The EXIF facts of the photo at ``path`` (:class:`PhotoMeta`); never raises.

    Parameters
    ----------
    path : str
        An image file. Not a regular file, unreadable, not an image, no EXIF: all None.

    Returns
    -------
    PhotoMeta
    """
    import os

    try:
        if not os.path.isfile(path):
            return PhotoMeta()
        from PIL import Image

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(path) as im:
                return _meta_of(im)
    except Exception:  # noqa: BLE001 - any problem with the file or its EXIF: nothing known
        return PhotoMeta()


def _meta_of(im) -> PhotoMeta:
    """:class:`PhotoMeta` of an opened PIL image (each tag read on its own)."""
    exif = _exif(im)
    gps = _ifd(exif, GPS_IFD)
    sub = _ifd(exif, EXIF_IFD)
    lat = _safe(_coordinate, gps, _LAT, _LAT_REF, "NS", 90.0)
    lon = _safe(_coordinate, gps, _LON, _LON_REF, "EW", 180.0)
    if lat is None or lon is None:
        lat = lon = None
    heading = _safe(_heading, gps)
    width, height = _safe(_oriented_size, im, exif) or (None, None)
    return PhotoMeta(taken_at=_safe(_taken_at, sub), lat_deg=lat, lon_deg=lon, alt_m=_safe(_altitude, gps),
                     accuracy_m=_safe(_accuracy, gps), heading_deg=heading,
                     heading_ref=_safe(_heading_ref, gps) if heading is not None else None,
                     width=width, height=height)


def _safe(fn, *args) -> Any:
    try:
        return fn(*args)
    except Exception:  # noqa: BLE001 - garbage in one tag spoils only that value
        return None


def _exif(im):
    """The image's EXIF; for PNG only an ``eXIf`` chunk before the pixels (``getexif`` would
    decode the whole image to look after them)."""
    from PIL import Image

    if im.format == "PNG":
        exif = Image.Exif()
        raw = im.info.get("exif")
        if isinstance(raw, (bytes, bytearray)) and raw:
            exif.load(bytes(raw))
        return exif
    return im.getexif()


def _ifd(exif, tag: int) -> dict:
    try:
        d = exif.get_ifd(tag)
        return d if isinstance(d, dict) else {}
    except Exception:  # noqa: BLE001
        return {}


def _text(v: Any) -> Optional[str]:
    """An ASCII tag's value as stripped text (bytes decoded; NULs dropped), or None."""
    if isinstance(v, (bytes, bytearray)):
        v = bytes(v).decode("ascii", "replace")
    if not isinstance(v, str):
        return None
    v = v.replace("\x00", "").strip()
    return v or None


def _number(v: Any) -> Optional[float]:
    """A rational or number as a finite float (a 1-tuple unwrapped), or None."""
    if isinstance(v, (tuple, list)) and len(v) == 1:
        v = v[0]
    if isinstance(v, (bool, str, bytes, bytearray)) or v is None:
        return None
    x = float(v)
    return x if math.isfinite(x) else None


def dms_to_deg(dms: Any) -> Optional[float]:
    """EXIF degrees, minutes, seconds (1 to 3 non-negative rationals) as degrees, or None.

    Examples
    --------
    >>> dms_to_deg((48, 30, 36))
    48.51
    """
    if not isinstance(dms, (tuple, list)) or not 1 <= len(dms) <= 3:
        return None
    parts = [_number(x) for x in dms]
    if any(p is None or p < 0 for p in parts):
        return None
    return sum(p / 60.0 ** i for i, p in enumerate(parts))


def _coordinate(gps: dict, tag: int, ref_tag: int, refs: str, limit: float) -> Optional[float]:
    """Signed degrees of a GPS latitude or longitude; None without a valid hemisphere ``refs``."""
    deg = dms_to_deg(gps.get(tag))
    ref = (_text(gps.get(ref_tag)) or "").upper()
    if deg is None or deg > limit or len(ref) != 1 or ref not in refs:
        return None
    return -deg if ref == refs[1] else deg


def _altitude(gps: dict) -> Optional[float]:
    alt = _number(gps.get(_ALT))
    if alt is None or abs(alt) > 1e5:
        return None
    ref = gps.get(_ALT_REF, 0)
    if isinstance(ref, (bytes, bytearray)):
        ref = ref[0] if len(ref) else 0
    if ref not in (0, 1):
        return None
    return -alt if ref == 1 else alt


def _accuracy(gps: dict) -> Optional[float]:
    acc = _number(gps.get(_H_POS_ERROR))
    return acc if acc is not None and 0 <= acc < 1e6 else None


def _heading(gps: dict) -> Optional[float]:
    h = _number(gps.get(_IMG_DIR))
    if h is None or not 0 <= h <= 360:
        return None
    return h % 360.0


def _heading_ref(gps: dict) -> Optional[str]:
    ref = (_text(gps.get(_IMG_DIR_REF)) or "").upper()
    return ref if ref in ("T", "M") else None


def exif_datetime(value: Any, offset: Any = None) -> Optional[str]:
    """EXIF ``"YYYY:MM:DD HH:MM:SS"`` (and an ``"+HH:MM"`` offset) as ISO 8601 text, or None.

    Examples
    --------
    >>> exif_datetime("2026:05:14 10:32:07", "+02:00")
    '2026-05-14T10:32:07+02:00'
    """
    text = _text(value)
    if text is None:
        return None
    t = datetime.strptime(text[:19], "%Y:%m:%d %H:%M:%S")
    iso = t.isoformat(timespec="seconds")
    off = _text(offset)
    return iso + off if off and _OFFSET_RE.fullmatch(off) else iso


def _taken_at(sub: dict) -> Optional[str]:
    return exif_datetime(sub.get(_DATETIME_ORIGINAL), sub.get(_OFFSET_TIME_ORIGINAL))


def _oriented_size(im, exif) -> tuple[int, int]:
    """(width, height) after the EXIF orientation, as ``load_photo`` returns the photo."""
    w, h = (int(v) for v in im.size)
    o = exif.get(_ORIENTATION, 1)
    return (h, w) if o in _SWAPPING_ORIENTATIONS else (w, h)
