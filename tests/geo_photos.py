"""Synthetic photos with phone-like EXIF (GPS as rationals with N/S/E/W refs, GPSImgDirection,
DateTimeOriginal, orientation) for the field-record tests, written with Pillow at test time."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
from PIL import Image

from monodbh.toolkit.evaluation.phone_exif import dms, exif_for, rational

__all__ = ["rational", "dms", "exif_for", "write_photo"]


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
