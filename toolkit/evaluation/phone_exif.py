"""Phone-like EXIF for photos written by the evaluation tools and the tests: GPS position as
(degrees, minutes, seconds) rationals with N/S/E/W refs, altitude, horizontal accuracy,
``GPSImgDirection`` with its reference, ``DateTimeOriginal`` with its offset, orientation, as
phones write them (Pillow ``Image.Exif``).

Imported by :mod:`.position_bench` and the tests; imports Pillow.
"""
from __future__ import annotations

from fractions import Fraction
from typing import Optional

from PIL import Image
from PIL.TiffImagePlugin import IFDRational

__all__ = ["rational", "dms", "exif_for"]


def rational(x: float, den: int = 10000) -> IFDRational:
    """``x`` as an EXIF rational (as phones write them: integer numerator / denominator)."""
    f = Fraction(x).limit_denominator(den)
    return IFDRational(f.numerator, f.denominator)


def dms(deg: float) -> tuple:
    """|deg| as EXIF (degrees, minutes, seconds) rationals, seconds to 1/10000."""
    a = abs(deg)
    d = int(a)
    m = int((a - d) * 60)
    s = (a - d - m / 60) * 3600
    return (IFDRational(d, 1), IFDRational(m, 1), IFDRational(int(round(s * 10000)), 10000))


def exif_for(*, lat: Optional[float] = None, lon: Optional[float] = None, alt: Optional[float] = None,
             accuracy: Optional[float] = None, heading: Optional[float] = None, heading_ref: Optional[str] = "T",
             taken: Optional[str] = None, offset: Optional[str] = None, orientation: Optional[int] = None) -> Image.Exif:
    """An :class:`Image.Exif` with the given facts (None: tag left out)."""
    ex = Image.Exif()
    if orientation is not None:
        ex[0x0112] = orientation
    gps = ex.get_ifd(0x8825)
    if lat is not None:
        gps[1] = "N" if lat >= 0 else "S"
        gps[2] = dms(lat)
    if lon is not None:
        gps[3] = "E" if lon >= 0 else "W"
        gps[4] = dms(lon)
    if alt is not None:
        gps[5] = b"\x00" if alt >= 0 else b"\x01"
        gps[6] = rational(abs(alt), 100)
    if accuracy is not None:
        gps[31] = rational(accuracy, 100)
    if heading is not None:
        if heading_ref is not None:
            gps[16] = heading_ref
        gps[17] = rational(heading, 100)
    if taken is not None:
        sub = ex.get_ifd(0x8769)
        sub[0x9003] = taken
        if offset is not None:
            sub[0x9011] = offset
    return ex
