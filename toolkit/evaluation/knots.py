"""The stem's width by where the rope's knot sits: ``python -m monodbh.toolkit.evaluation.knots``.

A rope tied round the stem has a knot and two loose ends (the generator ties one on half of its
ropes, at a random angle round the stem). Tied on the stem's flank, as the camera sees it, the
knot sticks out past the silhouette and its loose ends hang beside the stem; tied at the front or
the back, it cannot widen the stem. The generator does not record the knot's angle: it is
recovered by drawing the scene again from the sample's seed (:func:`knot_out_fraction`, no
rendering). The table compares the width alone (``dbh eval``'s ``width_err_pct``) of the photos
whose knot sticks out with the others; it backs the photo protocol's advice on the knot.

Imported by nothing on the measuring path; imports ``monodbh.models.synthetic`` (the scene
sampler, not the renderer).

Examples
--------
``dbh eval data/bench -j 2 --json runs/eval/plain.json`` then
``python -m monodbh.toolkit.evaluation.knots data/bench runs/eval/plain.json`` (several folder and
report pairs are pooled).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

__all__ = ["knot_out_fraction", "knot_table", "OUT_MIN"]

#: a knot sticking out past the silhouette by more than this fraction of the stem's width counts
#: as "on the flank"
OUT_MIN = 0.01


def knot_out_fraction(meta: dict) -> Optional[float]:
    """How far the roped stem's knot sticks out past its silhouette at 1.3 m, as this camera sees
    it, over the silhouette's angular width (0 where it does not, or without a knot).

    Parameters
    ----------
    meta : a ``dbh synth`` sample's record (``dataset_seed``, ``index``, ``width``, ``height``,
        ``stand``, ``roped_tree``, ``t_world_from_cam``).

    Returns
    -------
    float >= 0, or None without a roped tree (or where the scene drawn again from the seed is not
    the recorded one).
    """
    from monodbh.models.synthetic import sample_seed
    from monodbh.models.synthetic.scene import sample_scene

    if meta.get("roped_tree") is None:
        return None
    s = sample_seed(int(meta["dataset_seed"]), int(meta["index"]))
    scene = sample_scene(np.random.default_rng(s), int(meta["width"]), int(meta["height"]), seed=s,
                         stand=meta.get("stand", "forest"))
    tree = scene.trees[int(meta["roped_tree"]) - 1]
    rec = next(t for t in meta["trees"] if t["id"] == meta["roped_tree"])
    if abs(tree.dbh_m() - float(rec["dbh_m"])) > 1e-9:
        return None
    ring = next(r for r in tree.rings if r.is_rope)
    if not ring.knot:
        return 0.0
    C = np.asarray(meta["t_world_from_cam"], np.float64)
    ax = tree.axis
    w = tree.axis_point(ring.s_m) - C
    w = w - (w @ ax) * ax
    w /= np.linalg.norm(w)
    u = np.cross(ax, w)
    th = np.linspace(0, 2 * np.pi, 2048, endpoint=False)
    V = tree.surface_point(th, np.full(th.shape, ring.s_m)) - C
    phi = np.arctan2(V @ u, V @ w)
    lo, hi = float(phi.min()), float(phi.max())
    # the generator's knot: a blob of radius 2.2 r, its centre 2 r off the surface (r >= 4-5 mm)
    k = tree.surface_point(np.array([ring.knot_theta]), np.array([ring.s_m]),
                           offset=2 * max(ring.tube_radius_m, 0.004))[0] - C
    half = 2.2 * max(ring.tube_radius_m, 0.005) / float(np.linalg.norm(k))
    pk = float(np.arctan2(k @ u, k @ w))
    return max(pk + half - hi, lo - (pk - half), 0.0) / (hi - lo)


def knot_table(folder: Path, records: Sequence[dict]) -> dict:
    """Width alone (``|width_err_pct|``) of the measured photos, knot on the flank against not.

    Returns
    -------
    ``{"flank": {...}, "other": {...}}``, each with ``photos``, ``median``, ``p90``,
    ``over_5pct``, ``errors`` (the width errors, %) and, for the flank, ``samples``
    (``[index, knot out %, width error %]``).
    """
    groups = {"flank": [], "other": []}
    for r in records:
        if r.get("width_err_pct") is None:
            continue
        meta = json.loads((Path(folder) / f"{int(r['sample']):06d}.json").read_text())
        f = knot_out_fraction(meta)
        if f is None:
            continue
        groups["flank" if f > OUT_MIN else "other"].append((int(r["sample"]), 100 * f, float(r["width_err_pct"])))
    out = {}
    for k, g in groups.items():
        e = np.abs([x[2] for x in g])
        out[k] = {"photos": len(g), "median": float(np.median(e)) if len(e) else None,
                  "p90": float(np.percentile(e, 90)) if len(e) else None, "over_5pct": int((e > 5).sum()),
                  "errors": [x[2] for x in g]}
        if k == "flank":
            out[k]["samples"] = [[i, round(f, 1), round(w, 1)] for i, f, w in g]
    return out


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("pairs", nargs="+", metavar="FOLDER EVAL_JSON",
                   help="a dbh synth folder and its dbh eval --json report (several pairs are pooled)")
    a = p.parse_args(argv)
    if len(a.pairs) % 2:
        p.error("give a dbh eval --json report after each folder")
    tables = [knot_table(Path(f), json.loads(Path(j).read_text())["samples"])
              for f, j in zip(a.pairs[::2], a.pairs[1::2])]
    print(f"{'knot':<40} {'photos':>6} {'median':>7} {'p90':>6} {'> 5 %':>6}")
    for k, name in (("flank", f"on the flank (out > {100 * OUT_MIN:.0f} % of the width)"),
                    ("other", "at the front or back, or none")):
        e = np.abs([x for t in tables for x in t[k]["errors"]])
        fmt = (lambda v: f"{v:.1f}")
        print(f"{name:<40} {len(e):>6} {fmt(np.median(e)) if len(e) else '-':>7} "
              f"{fmt(np.percentile(e, 90)) if len(e) else '-':>6} {int((e > 5).sum()):>6}")
    for (f, _), t in zip(zip(a.pairs[::2], a.pairs[1::2]), tables):
        print(f"{f}: knot on the flank [index, knot out %, width error %]:", t["flank"]["samples"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
