"""The crew's 1.3 m marker, kept in the camera file: :func:`read_marker_width_m`, :func:`write_marker_width`.

The marker's width (a rope's diameter, or a flat strap's width along the stem) is equipment,
set once per field kit, like the camera. It lives in the camera file the crew already passes to
every command (``--calib cam.yaml``) as one key, ``marker_width_mm``, that OpenCV and ROS
readers ignore; ``dbh marker CAM --width-mm W`` writes it, ``dbh measure --rope-mm`` overrides
it for one run. Imported by ``monodbh.cli``; imports :mod:`.camera_io` and :mod:`.errors`.
"""
from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any, Optional

from .errors import CameraFileError

__all__ = ["MARKER_KEY", "MARKER_WIDTH_RANGE_MM", "read_marker_width_m", "write_marker_width"]

#: the camera file's key holding the marker's width in millimetres
MARKER_KEY = "marker_width_mm"
#: accepted widths (mm): an 8 mm rope to a 50 mm strap, with room either side
MARKER_WIDTH_RANGE_MM = (1.0, 100.0)

_LINE = re.compile(rf"^{MARKER_KEY}\s*:.*$\n?", re.M)


def _check_width_mm(width_mm: float, p: Path) -> float:
    from .camera_io import _short

    lo, hi = MARKER_WIDTH_RANGE_MM
    try:
        w = float(width_mm)
    except (TypeError, ValueError):
        raise CameraFileError(f"{p}: '{MARKER_KEY}' must be a number, got {_short(width_mm)}") from None
    if not (math.isfinite(w) and lo <= w <= hi):
        raise CameraFileError(f"{p}: '{MARKER_KEY}' must be between {lo:g} and {hi:g} mm, got {_short(width_mm)}")
    return w


def read_marker_width_m(path: Any) -> Optional[float]:
    """The marker width stored in a camera file, in metres, or None when it holds none.

    Parameters
    ----------
    path : str or os.PathLike
        A camera file (OpenCV FileStorage YAML or ROS ``camera_info``).

    Raises
    ------
    CameraFileError
        The file cannot be read, or its ``marker_width_mm`` is not a width in range.

    Examples
    --------
    >>> read_marker_width_m("cam.yaml")          # doctest: +SKIP
    0.01
    """
    from .camera_io import _parse, _read_camera_text

    p = Path(path)
    data = _parse(_read_camera_text(p), p)
    if data.get(MARKER_KEY) is None:
        return None
    return _check_width_mm(data[MARKER_KEY], p) / 1000.0


def write_marker_width(path: Any, width_mm: Optional[float]) -> None:
    """Set (or with None remove) the marker width in a camera file, keeping every other line.

    The file must already be a camera file (it is read back as one before it is replaced);
    it is rewritten atomically (temporary file, then rename).

    Parameters
    ----------
    path : str or os.PathLike
        The camera file.
    width_mm : float or None
        The marker's width in millimetres (:data:`MARKER_WIDTH_RANGE_MM`); None removes it.

    Raises
    ------
    CameraFileError
        The file is missing, not a camera file, or cannot be written; the width is out of range.
    """
    from .camera_io import _camera_from_data, _parse, _read_camera_text, _write_text_atomic

    p = Path(path)
    new = _LINE.sub("", _read_camera_text(p))
    if width_mm is not None:
        w = _check_width_mm(width_mm, p)
        if new and not new.endswith("\n"):
            new += "\n"
        new += f"{MARKER_KEY}: {w:g}\n"
    _camera_from_data(_parse(new, p), p)            # still a camera file (and it was one)
    _write_text_atomic(p, new)
