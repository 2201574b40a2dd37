"""``dbh calibrate`` and ``dbh calibrate-pose``.

Importing this module costs only typer: numpy, OpenCV and ``monodbh.calib`` are imported inside
the commands. ``cli/main.py`` registers the two functions.
"""
from __future__ import annotations

import contextlib
import enum
import json
import time
from pathlib import Path
from typing import Iterator, List, Optional

import typer

__all__ = ["calibrate", "calibrate_pose"]


class Detector(str, enum.Enum):
    auto = "auto"
    sb = "sb"
    classic = "classic"


class FileFormat(str, enum.Enum):
    opencv = "opencv"
    ros = "ros"


@contextlib.contextmanager
def _user_errors() -> Iterator[None]:
    """Turn user-facing errors into ``error: <message>`` on stderr and exit status 1."""
    from monodbh.calib.errors import MonodbhError

    try:
        yield
    except MonodbhError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from None
    except KeyboardInterrupt:
        typer.echo("error: interrupted", err=True)
        raise typer.Exit(130) from None
    except MemoryError:
        typer.echo("error: out of memory (try fewer or smaller photos)", err=True)
        raise typer.Exit(1) from None
    except Exception as exc:  # cv2.error on input OpenCV rejects; anything else is a bug
        if type(exc).__module__.startswith("cv2"):
            lines = [ln for ln in str(exc).strip().splitlines() if ln.strip()]
            typer.echo(f"error: OpenCV: {lines[-1] if lines else exc}", err=True)
            raise typer.Exit(1) from None
        raise


def _make_board(board: str, square: float, charuco: bool, dictionary: str,
                marker: Optional[float], legacy: bool):
    from monodbh.calib.board import Board, parse_board_size

    try:
        cols, rows = parse_board_size(board)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--board") from None
    try:
        return Board(cols, rows, float(square), charuco=charuco, marker_m=marker,
                     dictionary=dictionary, legacy=legacy)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--board/--square/--marker/--dict") \
            from None


def _console():
    from rich.console import Console

    return Console(stderr=True, highlight=False, soft_wrap=True)


def _fmt_std(v: float, std: Optional[float], digits: int) -> str:
    s = f"{v:.{digits}f}"
    return s if std is None else f"{s} ± {std:.{digits}f}"


def _report(con, res, elapsed: float, output: Optional[Path], fmt: str) -> None:
    from rich.markup import escape

    cam = res.camera
    w, h = cam.image_size
    used, bad = res.used, res.rejected
    con.print(f"[bold]calibrated[/] {w}x{h} camera from {len(res.views)} images "
              f"({escape(res.board.describe())}) in {elapsed:.1f} s")
    con.print(f"views: {len(used)} used, {len(bad)} rejected")
    width = max(len(Path(v.name).name) for v in res.views)
    for v in res.views:
        name = escape(Path(v.name).name.ljust(width))
        n = "" if v.detection is None else f"{len(v.detection.ids):3d} corners"
        err = "" if v.error_px is None else f"rms {v.error_px:.3f} px"
        if v.status == "used":
            con.print(f"  {name}  [green]used[/]      {n}  {err}")
        else:
            tag = "rejected" if v.status == "rejected" else "failed  "
            con.print(f"  {name}  [red]{tag}[/]  {escape(v.reason or '')}")
    errs = [v.error_px for v in used]
    con.print(f"RMS reprojection error [bold]{res.rms:.3f} px[/] "
              f"(per view {min(errs):.3f} .. {max(errs):.3f} px)")
    sd = res.std
    for k, val in (("fx", cam.fx), ("fy", cam.fy), ("cx", cam.cx), ("cy", cam.cy)):
        con.print(f"  {k} = {_fmt_std(val, sd.get(k), 3)} px")
    names = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4",
             "tauX", "tauY")
    dist = "  ".join(f"{n} {_fmt_std(d, sd.get(n), 5)}" for n, d in zip(names, cam.dist))
    con.print(f"  distortion: {dist}")
    cov = "  ".join(f"{c.name} {c.progress:.0%}" for c in res.coverage)
    good = all(c.progress >= 1.0 for c in res.coverage)
    con.print(f"coverage (ROS camera_calibration scores): {cov}"
              + ("  [green]good[/]" if good else ""))
    if res.advice:
        con.print("[yellow]advice:[/]")
        for tip in res.advice:
            con.print(f"  - {escape(tip)}")
    if output is not None:
        kind = "OpenCV FileStorage YAML" if fmt == "opencv" else "ROS camera_info YAML"
        con.print(f"wrote {escape(str(output))} ({kind})")


def calibrate(
    images: List[Path] = typer.Argument(..., metavar="IMAGES...",
                                        help="Photos of the board (same size), 10-25 recommended."),
    board: str = typer.Option(..., "--board", "-b", metavar="COLSxROWS",
                              help="Chessboard inner corners (e.g. 9x6); with --charuco, squares "
                                   "(e.g. 7x5)."),
    square: float = typer.Option(..., "--square", "-s", min=0.0, help="Square side, metres."),
    output: Path = typer.Option(Path("cam.yaml"), "--output", "-o", help="Camera file to write."),
    file_format: FileFormat = typer.Option(FileFormat.opencv, "--format",
                                           help="opencv: OpenCV calibration-sample FileStorage "
                                                "YAML; ros: ROS camera_info YAML."),
    charuco: bool = typer.Option(False, "--charuco", help="The board is a ChArUco board."),
    dictionary: str = typer.Option("DICT_5X5_100", "--dict",
                                   help="ChArUco ArUco dictionary (OpenCV name)."),
    marker: Optional[float] = typer.Option(None, "--marker", min=0.0,
                                           help="ChArUco marker side, metres "
                                                "(default 0.75 x square)."),
    legacy: bool = typer.Option(False, "--legacy-charuco",
                                help="ChArUco board from OpenCV < 4.6 (even row count)."),
    detector: Detector = typer.Option(Detector.auto, "--detector",
                                      help="auto: findChessboardCornersSB, classic as fallback."),
    subpix_win: Optional[int] = typer.Option(None, "--subpix-win", min=0,
                                             help="cornerSubPix half window, px (default 0.3 x "
                                                  "corner spacing); 0 = no refinement."),
    detect_size: int = typer.Option(1000, "--detect-size", min=64,
                                    help="Detect on a copy this many px on its long side."),
    fix_aspect: bool = typer.Option(False, "--fix-aspect-ratio", help="Force fx = fy."),
    zero_tangent: bool = typer.Option(False, "--zero-tangent", help="No tangential distortion."),
    rational: bool = typer.Option(False, "--rational",
                                  help="8-coefficient rational distortion model."),
    non_planar: bool = typer.Option(False, "--non-planar",
                                    help="Board may not be flat: calibrateCameraRO "
                                         "(release-object)."),
    no_reject: bool = typer.Option(False, "--no-reject", help="Keep outlier views."),
    outlier_factor: float = typer.Option(3.0, "--outlier-factor", min=1.0,
                                         help="Reject views with error > this x median."),
    threads: Optional[int] = typer.Option(None, "--threads", "-j", min=1,
                                          help="Detection threads (default min(4, CPUs))."),
    debug_dir: Optional[Path] = typer.Option(None, "--debug-dir",
                                             help="Write an overlay per view (corners, residuals "
                                                  "x20) here."),
    as_json: bool = typer.Option(False, "--json", help="Print a JSON summary on stdout."),
) -> None:
    """Calibrate the camera from photos of a chessboard (or ChArUco board) and write cam.yaml."""
    with _user_errors():
        import cv2

        from monodbh.calib.calibration import calibrate as run_calibration
        from monodbh.calib.camera_io import save_camera

        b = _make_board(board, square, charuco, dictionary, marker, legacy)
        flags = 0
        if fix_aspect:
            flags |= cv2.CALIB_FIX_ASPECT_RATIO
        if zero_tangent:
            flags |= cv2.CALIB_ZERO_TANGENT_DIST
        if rational:
            flags |= cv2.CALIB_RATIONAL_MODEL
        con = _console()
        t0 = time.perf_counter()
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, \
            TimeRemainingColumn

        progress = Progress(TextColumn("detecting board"), BarColumn(), MofNCompleteColumn(),
                            TimeRemainingColumn(), console=con, transient=True,
                            disable=not con.is_terminal or len(images) < 4)
        with progress:
            task = progress.add_task("detect", total=len(images))
            res = run_calibration(
                images, b, detector=detector.value, max_side=detect_size, subpix_win=subpix_win,
                flags=flags, non_planar=non_planar, reject_outliers=not no_reject,
                outlier_factor=outlier_factor, threads=threads,
                progress=lambda done, total, name: progress.update(task, completed=done),
                keep_images=debug_dir is not None)
        if file_format is FileFormat.ros and res.camera.dist.size not in (4, 5, 8):
            raise typer.BadParameter("ROS camera_info holds 5 or 8 distortion coefficients",
                                     param_hint="--format")
        save_camera(res.camera, output, format=file_format.value)
        written = []
        if debug_dir is not None:
            from monodbh.calib.debug import write_debug_overlays

            written = write_debug_overlays(res, debug_dir)
        elapsed = time.perf_counter() - t0
        _report(con, res, elapsed, output, file_format.value)
        if written:
            con.print(f"wrote {len(written)} overlays to {debug_dir}")
        if as_json:
            d = res.to_dict()
            d.update(output=str(output), format=file_format.value, elapsed_s=elapsed,
                     debug_overlays=[str(p) for p in written])
            typer.echo(json.dumps(d, indent=2))


def _file_format(path: Path) -> str:
    try:
        return "opencv" if "!!opencv-matrix" in path.read_text(encoding="utf-8") else "ros"
    except (OSError, UnicodeDecodeError):
        return "opencv"


def calibrate_pose(
    board_photo: Path = typer.Argument(..., metavar="BOARD_PHOTO",
                                       help="Photo of the board lying flat on level ground, "
                                            "taken from the pole."),
    calib: Path = typer.Option(..., "--calib", "-c", help="cam.yaml from dbh calibrate."),
    board: str = typer.Option(..., "--board", "-b", metavar="COLSxROWS",
                              help="Chessboard inner corners (with --charuco: squares)."),
    square: float = typer.Option(..., "--square", "-s", min=0.0, help="Square side, metres."),
    output: Optional[Path] = typer.Option(None, "--output", "-o",
                                          help="Write here instead of updating --calib."),
    thickness: float = typer.Option(0.0, "--board-thickness", min=0.0,
                                    help="Board thickness, metres (added to the height)."),
    charuco: bool = typer.Option(False, "--charuco", help="The board is a ChArUco board."),
    dictionary: str = typer.Option("DICT_5X5_100", "--dict", help="ChArUco dictionary."),
    marker: Optional[float] = typer.Option(None, "--marker", min=0.0,
                                           help="ChArUco marker side, metres."),
    legacy: bool = typer.Option(False, "--legacy-charuco", help="OpenCV < 4.6 ChArUco layout."),
    as_json: bool = typer.Option(False, "--json", help="Print a JSON summary on stdout."),
) -> None:
    """Store the camera height, pitch and roll (from a board on the ground) in cam.yaml."""
    with _user_errors():
        from monodbh.calib.camera_io import load_camera, save_camera
        from monodbh.calib.pose import estimate_ground_pose

        b = _make_board(board, square, charuco, dictionary, marker, legacy)
        camera = load_camera(calib)
        res = estimate_ground_pose(board_photo, camera, b, board_thickness_m=thickness)
        from monodbh.calib.marker import read_marker_width_m, write_marker_width

        out = output or calib
        fmt = _file_format(calib)
        marker_m = read_marker_width_m(calib)
        save_camera(res.camera, out, format=fmt)
        if marker_m is not None:            # the crew's marker stays with the camera
            write_marker_width(out, marker_m * 1000.0)
        p = res.pose
        con = _console()
        look = "up" if p.pitch_deg > 0 else "down"
        con.print(f"board found: {res.n_corners} corners, reprojection RMS {res.rms_px:.3f} px, "
                  f"nearest corner {res.distance_m:.2f} m"
                  + (f", photo turned {res.rotation} deg" if res.rotation else ""))
        con.print(f"camera height [bold]{p.height_m:.3f} m[/] above ground, pitch "
                  f"[bold]{p.pitch_deg:+.2f}°[/] (looking {look}), roll [bold]{p.roll_deg:+.2f}°[/]")
        for wmsg in res.warnings:
            con.print(f"[yellow]warning:[/] {wmsg}")
        con.print(f"wrote pose to {out}")
        if as_json:
            typer.echo(json.dumps({
                "output": str(out), "height_m": p.height_m, "pitch_deg": p.pitch_deg,
                "roll_deg": p.roll_deg, "R_world_from_camera": p.R_world_from_camera.tolist(),
                "t_world_from_camera": p.t_world_from_camera.tolist(), "rms_px": res.rms_px,
                "n_corners": res.n_corners, "rotation_deg": res.rotation,
                "warnings": res.warnings}, indent=2))
