"""``dbh reconstruct``: the coarse 3D scene of one photo plus the refined tree clouds, as PLY/LAS.

Top-level imports stay light (typer only).
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .measure_cmd import fail, load_calib, make_backend, measure_fn_option, parse_pick, session_factory_option

__all__ = ["reconstruct", "FRAMES", "to_frame"]

#: Output frames: ``camera`` (OpenCV: x right, y down, z forward), ``level`` (x right, y forward,
#: z up, as if the camera were level) and ``world`` (the camera pose of the calibration file).
FRAMES = ("camera", "level", "world")


def _check_output(path: Path) -> Path:
    from monodbh.toolkit.outputs.cloud_io import CLOUD_EXTENSIONS

    if path.suffix.lower() not in CLOUD_EXTENSIONS:
        raise typer.BadParameter(f"{path}: unknown point-cloud extension {path.suffix or '(none)'!r}; "
                                 f"use one of {', '.join(CLOUD_EXTENSIONS)}", param_hint="-o/--output")
    return path


def to_frame(cloud, frame: str, camera=None, photo: Optional[str] = None):
    """``cloud`` (camera frame) expressed in ``frame`` (see :data:`FRAMES`).

    ``world`` needs ``camera.pose``; the pose is adapted to the photo's size/orientation with
    ``camera.for_image``.
    """
    import numpy as np

    from monodbh.toolkit.result import PointCloud

    if frame == "camera":
        return cloud
    if frame == "level":
        R, t = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]), np.zeros(3)
    else:
        from monodbh.calib import read_image_size

        cam = camera.for_image(*read_image_size(photo)) if photo else camera
        if cam.pose is None:
            raise ValueError("no pose")
        R, t = np.asarray(cam.pose.R_world_from_camera), np.asarray(cam.pose.t_world_from_camera)
    xyz = (np.asarray(cloud.xyz, np.float64) @ R.T + t).astype(np.float32)
    return PointCloud(xyz, cloud.rgb, cloud.tree_id, cloud.trunk)


def reconstruct(
    photo: str = typer.Argument(..., help="Photo of the roped tree.", show_default=False),
    calib: Path = typer.Option(..., "--calib", "-c", help="Camera file (cam.yaml from dbh calibrate).",
                               show_default=False),
    output: Path = typer.Option(..., "--output", "-o", help="scene.ply or scene.las (.laz with lazrs).",
                                show_default=False),
    frame: str = typer.Option("camera", "--frame", help="Coordinates: camera (x right, y down, "
                              "z forward), level (z up, y forward) or world (pose in --calib)."),
    pick: Optional[str] = typer.Option(None, "--pick", metavar="X,Y", help="Pixel on the roped tree "
                                       "(when several trees carry a rope).", show_default=False),
    base: Optional[str] = typer.Option(None, "--base", metavar="X,Y", help="Pixel where the roped stem "
                                       "meets the ground: sets the scale (see dbh measure --base).",
                                       show_default=False),
    rope_mm: Optional[float] = typer.Option(None, "--rope-mm", min=1.0, max=100.0, help="The rope's true "
                                            "diameter in mm: sets the scale where the rope is thick enough "
                                            "(see dbh measure --rope-mm).", show_default=False),
    as_json: bool = typer.Option(False, "--json", help="Print the measurement as one JSON line."),
    models_dir: Optional[Path] = typer.Option(None, "--models-dir", help="Folder of the ONNX models.",
                                              show_default=False),
    measure_fn: Optional[str] = measure_fn_option(what="reconstruct_photo"),
    session_factory: Optional[str] = session_factory_option(),
) -> None:
    """Reconstruct the scene (coarse cloud + refined tree clouds with tree_id) and write PLY/LAS.

    Points are in metres; ``tree_id`` is 0 for non-tree points and k for tree k. Both formats
    open in CloudCompare (PLY: scalar field tree_id; LAS: extra dimension tree_id).
    """
    import json

    _check_output(output)
    pick_xy = parse_pick(pick)
    base_xy = parse_pick(base, "--base")
    if frame not in FRAMES:
        raise typer.BadParameter(f"expected one of {', '.join(FRAMES)}, got {frame!r}", param_hint="--frame")
    camera = load_calib(calib)
    if frame == "world" and camera.pose is None:
        raise typer.BadParameter(f"{calib} has no camera pose (run dbh calibrate-pose)", param_hint="--frame")

    from monodbh.calib import MonodbhError
    from monodbh.toolkit.batch import DEFAULT_RECONSTRUCT, normalise_result
    from monodbh.toolkit.outputs.cloud_io import write_cloud

    from monodbh.toolkit.outputs.paths import check_file_target

    from .measure_cmd import check_outputs

    check_outputs([photo, calib], [("-o", output)])
    try:
        check_file_target(output, "-o")
    except MonodbhError as exc:
        raise fail(str(exc))
    backend = make_backend(measure_fn, session_factory, models_dir, default_fn=DEFAULT_RECONSTRUCT)
    if not Path(photo).is_file():
        raise fail(f"{photo}: no such file")
    kw: dict = {"pick_xy": pick_xy} if pick_xy else {}
    if base_xy:
        kw["base_xy"] = base_xy
    from .marker_cmd import marker_width_m
    rope_m, _ = marker_width_m(calib, rope_mm)
    if rope_m is not None:
        kw["rope_diameter_m"] = rope_m
    res, cloud = _run(backend, photo, camera, kw)
    res = normalise_result(res, photo)
    cloud = to_frame(cloud, frame, camera, photo)
    try:
        write_cloud(output, cloud)
    except MonodbhError as exc:
        raise fail(str(exc))
    if as_json:
        from monodbh.toolkit.outputs.results_file import printable_row

        typer.echo(json.dumps(printable_row(res.to_json_dict()), ensure_ascii=False))
    _print_summary(res, cloud, output, frame)


def _run(backend, photo: str, camera, kw: dict):
    """Call the reconstruct function; returns (MeasureResult, PointCloud) or exits with a one-line error."""
    from monodbh.calib import MonodbhError
    from monodbh.toolkit.batch import error_result, one_line
    from monodbh.toolkit.result import MeasureResult, PointCloud

    try:
        fn = backend.function()
        session = backend.new_session()
        out = fn(photo, camera, session=session, **kw)
    except MonodbhError as exc:
        raise fail(str(exc))
    except Exception as exc:  # no traceback for the user; the message names the exception
        raise fail(one_line(error_result(photo, exc).error))
    if not (isinstance(out, tuple) and len(out) == 2 and isinstance(out[0], MeasureResult)):
        raise fail(f"internal error: reconstruct function returned {type(out).__name__}, "
                   f"expected (MeasureResult, PointCloud)")
    res, cloud = out
    if isinstance(cloud, (list, tuple)):
        cloud = PointCloud.concat(list(cloud))
    if cloud is None or not len(cloud):
        msg = res.error if getattr(res, "error", None) else "no 3D points reconstructed"
        raise fail(f"{photo}: {msg}" if not msg.startswith(str(photo)) else msg)
    return res, cloud


def _print_summary(res, cloud, output: Path, frame: str) -> None:
    """One line on the cloud written and one on the measured tree, on stderr."""
    import numpy as np
    from rich.console import Console

    from monodbh.toolkit.outputs.overlay import format_dbh

    ids = np.unique(np.asarray(cloud.tree_id))
    n_trees = int((ids > 0).sum())
    con = Console(stderr=True, highlight=False, soft_wrap=True)
    trunk = "" if cloud.trunk is None else f", {int(np.count_nonzero(cloud.trunk)):,} on trunks"
    con.print(f"{output}: {len(cloud):,} points{trunk}, {n_trees} tree{'s' if n_trees != 1 else ''} "
              f"({frame} frame)")
    if res.error:
        con.print(f"measured tree: {res.error}", style="yellow")
    else:
        dist = f" at {res.distance_m:.2f} m" if res.distance_m is not None else ""
        con.print(f"measured tree {res.tree_id if res.tree_id is not None else ''}: DBH "
                  f"{format_dbh(res.dbh_cm, res.dbh_sigma_cm)}{dist}".replace("tree :", "tree:"))
