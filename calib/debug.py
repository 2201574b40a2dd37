"""Debug overlays of a calibration: detected corners and magnified reprojection residuals."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .board import Board
from .calibration import CalibrationResult, ViewResult
from .errors import CalibrationError

__all__ = ["draw_view_overlay", "write_debug_overlays"]

_GREEN, _RED, _YELLOW, _CYAN = (60, 200, 60), (40, 40, 230), (0, 220, 255), (255, 200, 0)


def draw_view_overlay(view: ViewResult, board: Board, image_size: tuple[int, int], *,
                      magnify: float = 20.0) -> np.ndarray:
    """Draw one view: corners, residual arrows (``magnify`` x) and a status line.

    Parameters
    ----------
    view : ViewResult
        A view with ``thumbnail`` (from ``calibrate(..., keep_images=True)``).
    board : Board
        The board.
    image_size : tuple of int
        ``(width, height)`` of the full-resolution image.
    magnify : float, optional
        Residual arrows are drawn this many times longer than the residuals.

    Returns
    -------
    numpy.ndarray
        (h, w, 3) uint8 BGR overlay, 1280 to 1600 px on its long side.
    """
    import cv2

    if view.thumbnail is None:
        raise ValueError("view has no thumbnail; calibrate with keep_images=True")
    thumb = view.thumbnail
    if max(thumb.shape) < 1280:  # draw small images enlarged so marks and text stay legible
        f = 1280 / max(thumb.shape)
        thumb = cv2.resize(thumb, (int(round(thumb.shape[1] * f)), int(round(thumb.shape[0] * f))),
                           interpolation=cv2.INTER_LINEAR)
    th, tw = thumb.shape[:2]
    out = cv2.cvtColor(thumb, cv2.COLOR_GRAY2BGR)
    sx, sy = tw / image_size[0], th / image_size[1]

    def to_thumb(p: np.ndarray) -> np.ndarray:
        q = np.empty_like(p, dtype=np.float64)
        q[:, 0] = (p[:, 0] + 0.5) * sx - 0.5
        q[:, 1] = (p[:, 1] + 0.5) * sy - 0.5
        return q

    lw = max(1, int(round(max(th, tw) / 800)))
    det = view.detection
    if det is not None:
        pts = to_thumb(det.corners.astype(np.float64))
        if not board.charuco and len(pts) == board.n_corners:
            cv2.drawChessboardCorners(out, board.corner_grid,
                                      pts.reshape(-1, 1, 2).astype(np.float32), True)
        else:
            for p in pts:
                cv2.circle(out, (int(round(p[0])), int(round(p[1]))), 3 * lw, _CYAN, lw,
                           cv2.LINE_AA)
        if view.residuals is not None:
            colour = _GREEN if view.status == "used" else _RED
            ends = pts + magnify * view.residuals * np.array([sx, sy])
            for a, b in zip(pts, ends):
                cv2.arrowedLine(out, (int(round(a[0])), int(round(a[1]))),
                                (int(round(b[0])), int(round(b[1]))), colour, lw + 1,
                                cv2.LINE_AA, tipLength=0.25)
    if view.status == "used":
        text = f"used  rms {view.error_px:.3f} px  (residuals x{magnify:g})"
        colour = _GREEN
    elif view.status == "rejected":
        err = f"rms {view.error_px:.3f} px  " if view.error_px is not None else ""
        text = f"REJECTED {err}- {view.reason}"
        colour = _RED
    else:
        text = f"FAILED - {view.reason}"
        colour = _RED
    scale = max(th, tw) / 1280
    for txt, y in ((Path(view.name).name, 1), (text, 2)):
        org = (int(12 * scale), int(34 * scale * y))
        cv2.putText(out, txt, org, cv2.FONT_HERSHEY_SIMPLEX, 0.8 * scale, (0, 0, 0),
                    max(3, int(round(5 * scale))), cv2.LINE_AA)
        cv2.putText(out, txt, org, cv2.FONT_HERSHEY_SIMPLEX, 0.8 * scale,
                    colour if y == 2 else _YELLOW, max(1, int(round(2 * scale))), cv2.LINE_AA)
    return out


def write_debug_overlays(result: CalibrationResult, directory: Any, *,
                         magnify: float = 20.0) -> list[Path]:
    """Write one JPEG overlay per view into ``directory`` (created if needed).

    Files are named ``NNN_<stem>.jpg`` in input order.

    Returns
    -------
    list of pathlib.Path
        The files written.

    Raises
    ------
    CalibrationError
        The directory cannot be created or written.
    """
    import cv2

    d = Path(directory)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CalibrationError(f"{d}: cannot create debug directory ({exc.strerror or exc})") \
            from None
    size = result.camera.image_size
    written = []
    for i, v in enumerate(result.views):
        if v.thumbnail is None:
            continue
        img = draw_view_overlay(v, result.board, size, magnify=magnify)
        stem = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in Path(v.name).stem)
        path = d / f"{i:03d}_{stem or 'image'}.jpg"
        try:
            ok = cv2.imwrite(str(path), img, [cv2.IMWRITE_JPEG_QUALITY, 90])
        except cv2.error:
            ok = False
        if not ok:
            raise CalibrationError(f"{path}: cannot write debug overlay")
        written.append(path)
    return written
