"""``dbh marker``: store the width of the crew's 1.3 m marker (rope or strap) in the camera file."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .measure_cmd import fail

__all__ = ["marker", "marker_width_m"]


def marker(
    calib: Path = typer.Argument(..., help="Camera file (cam.yaml) to keep the marker's width in.",
                                 show_default=False),
    width_mm: Optional[float] = typer.Option(None, "--width-mm", min=1.0, max=100.0,
                                             help="The marker's width in mm: a rope's diameter, or a flat "
                                                  "strap's width along the stem.", show_default=False),
    clear: bool = typer.Option(False, "--clear", help="Remove the stored width."),
) -> None:
    """Set, show or clear the marker width that dbh measure uses as a ruler (--rope-mm overrides it).

    The width is equipment: set it once per rope or strap; it travels in cam.yaml as the key
    ``marker_width_mm``, which the rest of the file's readers ignore.
    """
    from monodbh.calib import MonodbhError
    from monodbh.calib.marker import read_marker_width_m, write_marker_width

    if width_mm is not None and clear:
        raise typer.BadParameter("give --width-mm or --clear, not both", param_hint="--clear")
    try:
        if width_mm is not None or clear:
            write_marker_width(calib, None if clear else width_mm)
        w = read_marker_width_m(calib)
    except MonodbhError as exc:
        raise fail(str(exc))
    if w is None:
        typer.echo(f"{calib}: no marker width (dbh measure reads the scale from the stem base or the "
                   f"depth network; set one with dbh marker {calib} --width-mm W)")
    else:
        typer.echo(f"{calib}: marker width {w * 1000:g} mm")


def marker_width_m(calib: Path, rope_mm: Optional[float]) -> tuple[Optional[float], Optional[str]]:
    """The marker width for a run (metres) and where it came from: ``--rope-mm``, else the
    camera file's ``marker_width_mm``, else ``(None, None)``. Exits with ``error: ...`` when the
    camera file's width is invalid."""
    from monodbh.calib import MonodbhError
    from monodbh.calib.marker import read_marker_width_m

    if rope_mm is not None:
        return rope_mm / 1000.0, "--rope-mm"
    try:
        w = read_marker_width_m(calib)
    except MonodbhError as exc:
        raise fail(str(exc))
    return (w, str(calib)) if w is not None else (None, None)
