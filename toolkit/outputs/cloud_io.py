"""Point-cloud files: PLY (plyfile) and LAS/LAZ (laspy), readable by CloudCompare.

Formats (chosen from the file extension, case-insensitive)
-----------------------------------------------------------
``.ply``
    ``binary_little_endian`` PLY with one ``vertex`` element: ``x, y, z`` float32 (metres),
    ``red, green, blue`` uchar, ``tree_id`` int32, and ``trunk`` uchar (1 on a trunk: a tree's
    stem, not its limbs or foliage) where the cloud knows it.
``.las`` / ``.laz``
    LAS 1.4, point format 7 (XYZ + RGB + GPS time), scale 0.001 m, offsets the floor of the
    minimum coordinate of each axis (whole metres); RGB scaled to 16 bit (``v * 257``);
    ``classification`` 5 (high vegetation) where ``tree_id > 0`` else 1 (unclassified); an
    extra-bytes dimension ``tree_id`` (int32), and ``trunk`` (uint8, as in PLY) where the
    cloud knows it. ``.laz`` needs a laspy LAZ backend
    (``pip install lazrs``).

Both writers are atomic: the file is written under a temporary name in the same folder and
renamed over the target, so a crash never leaves a half-written cloud.

:func:`read_cloud` reads both formats back (also PLY files exported by CloudCompare, which
renames scalar fields ``scalar_<name>``).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Union

import numpy as np

from monodbh.calib.errors import MonodbhError

from ..result import PointCloud
from .atomic import atomic_path

__all__ = ["write_cloud", "read_cloud", "CloudFileError", "CLOUD_EXTENSIONS", "cloud_format"]

PathLike = Union[str, "os.PathLike[str]"]

#: Extensions understood by :func:`write_cloud` / :func:`read_cloud`.
CLOUD_EXTENSIONS = (".ply", ".las", ".laz")

LAS_SCALE_M = 0.001


class CloudFileError(MonodbhError):
    """A point-cloud file cannot be written or read (unknown extension, I/O, bad content)."""


def cloud_format(path: PathLike) -> str:
    """``"ply"``, ``"las"`` or ``"laz"`` from the extension of ``path``.

    Raises
    ------
    CloudFileError
        Unknown extension.
    """
    ext = Path(path).suffix.lower()
    if ext not in CLOUD_EXTENSIONS:
        raise CloudFileError(f"{path}: unknown point-cloud extension {ext or '(none)'!r}; "
                             f"use one of {', '.join(CLOUD_EXTENSIONS)}")
    return ext[1:]


def _check_trunk(cloud: PointCloud, n: int) -> np.ndarray | None:
    if cloud.trunk is None:
        return None
    tr = np.asarray(cloud.trunk).reshape(-1)
    if len(tr) != n:
        raise ValueError(f"cloud arrays disagree: xyz {n}, trunk {len(tr)}")
    return tr.astype(bool).astype(np.uint8)


def _check_cloud(cloud: PointCloud) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xyz = np.asarray(cloud.xyz, dtype=np.float32).reshape(-1, 3)
    n = len(xyz)
    rgb = np.asarray(cloud.rgb)
    rgb = np.zeros((n, 3), np.uint8) if rgb.size == 0 and n else rgb.reshape(-1, 3)
    tid = np.asarray(cloud.tree_id)
    tid = np.zeros(n, np.int32) if tid.size == 0 and n else tid.reshape(-1)
    if len(rgb) != n or len(tid) != n:
        raise ValueError(f"cloud arrays disagree: xyz {n}, rgb {len(rgb)}, tree_id {len(tid)}")
    if not np.all(np.isfinite(xyz)):
        raise ValueError("cloud xyz contains NaN or infinity")
    return xyz, np.clip(rgb, 0, 255).astype(np.uint8), tid.astype(np.int32)


def _write_ply(tmp: str, xyz: np.ndarray, rgb: np.ndarray, tid: np.ndarray, trunk: np.ndarray | None) -> None:
    from plyfile import PlyData, PlyElement

    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
              ("tree_id", "<i4")] + ([("trunk", "u1")] if trunk is not None else [])
    v = np.empty(len(xyz), dtype=fields)
    v["x"], v["y"], v["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    v["red"], v["green"], v["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    v["tree_id"] = tid
    comment = "monodbh point cloud: metres; tree_id 0 = not a tree"
    if trunk is not None:
        v["trunk"] = trunk
        comment += "; trunk 1 = on a trunk"
    PlyData([PlyElement.describe(v, "vertex")], text=False, byte_order="<", comments=[comment]).write(tmp)


def _write_las(tmp: str, xyz: np.ndarray, rgb: np.ndarray, tid: np.ndarray, compress: bool,
               trunk: np.ndarray | None = None) -> None:
    import laspy

    if compress and not laspy.LazBackend.detect_available():
        raise CloudFileError("writing .laz needs a LAZ backend (pip install lazrs); "
                             "or write .las")
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.add_extra_dim(laspy.ExtraBytesParams(name="tree_id", type=np.int32,
                                                description="tree instance, 0 = none"))
    if trunk is not None:
        header.add_extra_dim(laspy.ExtraBytesParams(name="trunk", type=np.uint8,
                                                    description="1 = on a trunk"))
    header.scales = np.full(3, LAS_SCALE_M)
    header.offsets = np.floor(xyz.min(axis=0)).astype(np.float64) if len(xyz) else np.zeros(3)
    header.generating_software = "monodbh"
    las = laspy.LasData(header)
    las.x, las.y, las.z = (xyz[:, i].astype(np.float64) for i in range(3))
    rgb16 = rgb.astype(np.uint16) * np.uint16(257)
    las.red, las.green, las.blue = rgb16[:, 0], rgb16[:, 1], rgb16[:, 2]
    las.classification = np.where(tid > 0, 5, 1).astype(np.uint8)
    las.tree_id = tid
    if trunk is not None:
        las.trunk = trunk
    with open(tmp, "wb") as f:
        las.write(f, do_compress=compress)


def write_cloud(path: PathLike, cloud: PointCloud) -> Path:
    """Write ``cloud`` to ``path`` (PLY, LAS or LAZ from the extension), atomically.

    Parameters
    ----------
    path : str or os.PathLike
        Target file; its folder is created.
    cloud : PointCloud
        ``xyz`` (N, 3) metres, ``rgb`` (N, 3) uint8, ``tree_id`` (N,) int, ``trunk`` (N,) bool
        or None.

    Returns
    -------
    Path
        The written file.

    Raises
    ------
    CloudFileError
        Unknown extension, missing LAZ backend, or an I/O error (one line naming the file).
    ValueError
        Inconsistent or non-finite arrays (a programming error).
    """
    p = Path(path)
    fmt = cloud_format(p)
    xyz, rgb, tid = _check_cloud(cloud)
    trunk = _check_trunk(cloud, len(xyz))
    try:
        if fmt == "ply":
            with atomic_path(p) as tmp:
                _write_ply(tmp, xyz, rgb, tid, trunk)
        else:
            with atomic_path(p) as tmp:
                _write_las(tmp, xyz, rgb, tid, fmt == "laz", trunk)
    except CloudFileError as exc:
        raise CloudFileError(f"{p}: {exc}") from None
    except OSError as exc:
        raise CloudFileError(f"{p}: cannot write ({exc.strerror or exc})") from None
    return p


def _field(names, data, *candidates):
    for c in candidates:
        if c in names:
            return np.asarray(data[c])
    return None


def _read_ply(p: Path) -> PointCloud:
    from plyfile import PlyData

    ply = PlyData.read(str(p))
    if "vertex" not in [e.name for e in ply.elements]:
        raise CloudFileError(f"{p}: PLY file has no vertex element")
    v = ply["vertex"].data
    names = v.dtype.names or ()
    if not {"x", "y", "z"} <= set(names):
        raise CloudFileError(f"{p}: PLY vertices have no x, y, z")
    xyz = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32)
    cols = [_field(names, v, c, c[0]) for c in ("red", "green", "blue")]
    rgb = (np.stack(cols, axis=1) if all(c is not None for c in cols)
           else np.zeros((len(xyz), 3))).astype(np.uint8)
    tid = _field(names, v, "tree_id", "scalar_tree_id")
    tid = np.zeros(len(xyz), np.int32) if tid is None else np.rint(tid).astype(np.int32)
    tr = _field(names, v, "trunk", "scalar_trunk")
    return PointCloud(xyz, rgb, tid, None if tr is None else np.rint(tr).astype(np.int64) > 0)


def _read_las(p: Path) -> PointCloud:
    import laspy

    las = laspy.read(str(p))
    xyz = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1).astype(np.float32)
    dims = set(las.point_format.dimension_names)
    if {"red", "green", "blue"} <= dims:
        rgb = np.stack([np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)], axis=1)
        rgb = (rgb // 257 if rgb.size and rgb.max() > 255 else rgb).astype(np.uint8)
    else:
        rgb = np.zeros((len(xyz), 3), np.uint8)
    tid = np.asarray(las.tree_id).astype(np.int32) if "tree_id" in dims else np.zeros(len(xyz), np.int32)
    tr = np.asarray(las.trunk) > 0 if "trunk" in dims else None
    return PointCloud(xyz, rgb, tid, tr)


def read_cloud(path: PathLike) -> PointCloud:
    """Read a PLY/LAS/LAZ file written by :func:`write_cloud` (or a compatible tool).

    Missing colours read as black, a missing ``tree_id`` as 0 and a missing ``trunk`` as None.

    Raises
    ------
    CloudFileError
        Missing file, unknown extension or unreadable content.
    """
    p = Path(path)
    fmt = cloud_format(p)
    if not p.is_file():
        raise CloudFileError(f"{p}: no such file")
    try:
        return _read_ply(p) if fmt == "ply" else _read_las(p)
    except CloudFileError:
        raise
    except Exception as exc:  # plyfile/laspy raise many kinds
        msg = " ".join(str(exc).split()) or type(exc).__name__
        raise CloudFileError(f"{p}: cannot read {fmt.upper()} ({msg})") from None
