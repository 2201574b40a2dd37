"""Synthetic photos with phone-like EXIF (GPS as rationals with N/S/E/W refs, GPSImgDirection,
DateTimeOriginal, orientation) for the field-record tests, written with Pillow at test time."""
from __future__ import annotations

from fractions import Fraction
from pathlib import Path
from typing import Optional

import numpy as np
from PIL import Image
from PIL.TiffImagePlugin import IFDRational

__all__ = ["rational", "dms", "exif_for", "write_photo"]


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


def write_photo(path: Path, size=(64, 48), exif: Optional[Image.Exif] = None, seed: int = 0) -> Path:
    """A random RGB photo of ``size`` (stored width, height) with ``exif`` (None: no EXIF at all)."""
    w, h = size
    arr = np.random.default_rng(seed).integers(40, 255, (h, w, 3), dtype=np.uint8)
    im = Image.fromarray(arr)
    path = Path(path)
    if exif is None:
        im.save(path)
    else:  # as bytes: Pillow's PNG writer skips an Exif object whose first IFD is empty
        im.save(path, exif=exif.tobytes())
    return path
