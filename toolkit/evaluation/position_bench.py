"""Tree positions on benchmark photos: how far the measured tree is from the true one.

Each photo of a ``dbh synth`` folder is copied with phone-like EXIF (GPS position as rationals,
a true-north compass heading; seeded), measured with its own camera as ``dbh eval`` does, and
the tree position of its row (``tree_lat_deg``/``tree_lon_deg``: the camera moved the measured
horizontal distance along the stem's bearing) compared with the true one: the camera moved the
true horizontal distance to the roped stem's axis at 1.3 m along its true bearing (the heading
plus the true angle between the optical axis and the stem, both horizontal, from the record's
pose). GPS and compass are exact here, so the error is the pipeline's own: its distance and the
stem's bearing from the rope pixel. In the field the phone's GPS (3-10 m under a canopy) and
compass add theirs.

Usage::

    python -m monodbh.toolkit.evaluation.position_bench data/bench --count 40 [--workers 2] [--seed 25]

Imports the library, ``.synth_eval``, ``.phone_exif`` and Pillow; never imported by it.
"""
from __future__ import annotations

import argparse
import math
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

__all__ = ["true_tree_position", "exif_with_gps", "position_errors", "main"]


def _bearing_deg(v: np.ndarray) -> float:
    """Compass bearing of a world vector (x east, y north, z up), degrees."""
    return math.degrees(math.atan2(float(v[0]), float(v[1])))


def true_tree_position(meta: dict, lat_deg: float, lon_deg: float, heading_deg: float) -> Optional[tuple]:
    """(lat, lon, horizontal distance m, bearing deg) of the roped stem's axis at 1.3 m, for a
    camera at ``(lat_deg, lon_deg)`` whose optical axis points to ``heading_deg``; None without
    a roped tree."""
    from monodbh.toolkit.outputs.geo import destination

    tree = next((t for t in meta.get("trees", []) if t.get("id") == meta.get("roped_tree")), None)
    if tree is None or "bh_point_cam" not in tree:
        return None
    R = np.asarray(meta["R_world_from_cam"], np.float64)
    v = R @ np.asarray(tree["bh_point_cam"], np.float64)
    off = (_bearing_deg(v) - _bearing_deg(R[:, 2]) + 540.0) % 360.0 - 180.0
    bearing = (heading_deg + off) % 360.0
    horizontal = math.hypot(v[0], v[1])
    lat, lon = destination(lat_deg, lon_deg, bearing, horizontal)
    return lat, lon, horizontal, bearing


def _distance_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    """Metres between two WGS 84 points (pyproj's geodesic; else the ellipsoid's local radii,
    within a millimetre at these distances)."""
    try:
        from pyproj import Geod
    except ImportError:
        from monodbh.toolkit.outputs.geo import _E2, WGS84_A

        phi = math.radians((lat1 + lat2) / 2)
        w = 1.0 - _E2 * math.sin(phi) ** 2
        north = math.radians(lat2 - lat1) * WGS84_A * (1 - _E2) / w ** 1.5
        east = math.radians(lon2 - lon1) * WGS84_A / math.sqrt(w) * math.cos(phi)
        return math.hypot(east, north)
    return float(Geod(ellps="WGS84").inv(lon1, lat1, lon2, lat2)[2])


def exif_with_gps(lat_deg: float, lon_deg: float, heading_deg: float):
    """A Pillow ``Exif`` with GPS latitude/longitude and a true-north ``GPSImgDirection``, as
    phones write them (:func:`.phone_exif.exif_for`)."""
    from .phone_exif import exif_for

    return exif_for(lat=lat_deg, lon=lon_deg, heading=heading_deg % 360.0, heading_ref="T")


def position_errors(folder: Path, indices: Sequence[int], *, workers: int = 1, seed: int = 25,
                    rope_known: bool = False) -> list[dict]:
    """Measure ``indices`` of ``folder`` with seeded EXIF GPS and heading; a record per roped photo.

    Returns
    -------
    list of dict
        ``photo``, ``scale_source``, ``error`` (the row's), ``position_error_m``,
        ``bearing_error_deg``, ``true_horizontal_m`` (None where nothing was measured).
    """
    from PIL import Image

    from monodbh.toolkit.batch import Backend, iter_results
    from .synth_eval import eval_jobs, read_eval_samples

    samples = [s for s in read_eval_samples(Path(folder), indices) if s.gt_dbh_cm is not None]
    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory(prefix="monodbh-pos-") as tmp:
        jobs, truth = [], []
        for job, s in zip(eval_jobs(samples, rope_known=rope_known), samples):
            lat, lon, heading = 46.5 + rng.uniform(0, 0.01), 6.6 + rng.uniform(0, 0.01), rng.uniform(0, 360)
            copy = Path(tmp) / Path(job.photo).name
            with Image.open(job.photo) as im:
                im.save(copy, quality=95, exif=exif_with_gps(lat, lon, heading))
            jobs.append(replace(job, photo=str(copy)))
            truth.append(true_tree_position(s.meta, lat, lon, heading))
        out = []
        for res, t in zip(iter_results(jobs, Backend(), workers=workers), truth):
            rec = {"photo": Path(res.photo).name, "scale_source": res.scale_source, "error": res.error,
                   "position_error_m": None, "bearing_error_deg": None,
                   "true_horizontal_m": None if t is None else t[2]}
            if t is not None and res.tree_lat_deg is not None:
                rec["position_error_m"] = _distance_m(t[0], t[1], res.tree_lat_deg, res.tree_lon_deg)
                rec["bearing_error_deg"] = (res.stem_bearing_deg - t[3] + 540.0) % 360.0 - 180.0
            out.append(rec)
    return out


_GEOMETRIC = ("stem_base", "rope_diameter", "pose")


def _row(label: str, e: np.ndarray) -> str:
    if not len(e):
        return f"| {label} | 0 | - | - | - |"
    return (f"| {label} | {len(e)} | {np.median(e):.2f} | {np.percentile(e, 90):.2f} | "
            f"{np.mean(e <= 0.5) * 100:.0f} % |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m monodbh.toolkit.evaluation.position_bench",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("folder", type=Path, help="a dbh synth folder (e.g. data/bench)")
    ap.add_argument("--count", type=int, default=40, help="photos 0..count-1")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--seed", type=int, default=25, help="seeds the GPS positions and headings")
    ap.add_argument("--rope-known", action="store_true", help="give each photo its marker's true width")
    a = ap.parse_args(argv)
    recs = position_errors(a.folder, range(a.count), workers=a.workers, seed=a.seed, rope_known=a.rope_known)
    e = np.array([r["position_error_m"] for r in recs if r["position_error_m"] is not None])
    b = np.array([abs(r["bearing_error_deg"]) for r in recs if r["bearing_error_deg"] is not None])
    geo = np.array([r["position_error_m"] for r in recs if r["position_error_m"] is not None
                    and any(g in (r["scale_source"] or "") for g in _GEOMETRIC)])
    net = np.array([r["position_error_m"] for r in recs if r["position_error_m"] is not None
                    and not any(g in (r["scale_source"] or "") for g in _GEOMETRIC)])
    print(f"{a.folder}: {len(recs)} roped photos, {len(e)} with a tree position")
    print("| scale from | trees | median error, m | p90, m | within 0.5 m |\n|---|---|---|---|---|")
    print(_row("all", e))
    print(_row("geometry (stem base, marker)", geo))
    print(_row("depth network only", net))
    if len(b):
        print(f"stem bearing |error|: median {np.median(b):.2f} deg, max {b.max():.2f} deg")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
