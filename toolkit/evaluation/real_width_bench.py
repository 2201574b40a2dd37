"""Real photos, a rope painted across each hand-outlined trunk: is the stem's width at the rope right?

The first figure on real photos with a ground truth. Each outlined trunk of the 24 real photos
(``data/real_trees_outlines.json``, :mod:`.real_trunk_bench`) at least :data:`MIN_WIDTH_PX` wide
gets a red rope painted across it (:func:`.real_rope_bench.paint_rope`, the outline's run at the
chosen row: a row where the outline is one run, steady in width above and below), one trunk and
one thickness per painted photo. The photo is then measured as a user would (``measure_photo``,
no pick, or with ``--tap`` a tap on the painted rope's middle; a default camera fx = 0.8 x width) and the stem's width the pipeline took at the rope
(its edge pair, photo pixels) is compared with the outline's width along the same line.

This is the width alone (the scale has no truth on these photos): the part of the DBH that the
segmenter, the edge search and the rope check give on real bark, foliage and backgrounds. The
outlines were drawn by eye on photos 400-600 px tall; their edges are good to about 1-2 px, so
on trunks of 20-80 px the truth itself is good to a few per cent.

Usage::

    python -m monodbh.toolkit.evaluation.real_width_bench ../shared/data/real_trees [--out-dir runs/real_width] [--tap]

Imported by nothing (a command); imports the pipeline, the segmenter's outlines bench and
``monodbh.calib``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from .real_rope_bench import paint_rope
from .real_trunk_bench import MIN_WIDTH_PX, OUTLINES, load_outlines, rasterize

__all__ = ["RATIOS", "outline_row", "run_width", "line_run", "run", "summarise", "main"]

#: painted rope thickness as a fraction of the trunk's width (a 1 cm rope and a 3 cm strap on a
#: 20 cm stem)
RATIOS = (0.05, 0.15)
#: rows tried, as fractions of the outline's height from its top (the lower half first)
ROW_FRACTIONS = (0.6, 0.7, 0.5, 0.8, 0.4, 0.3)


def run_width(mask: np.ndarray, row: int) -> Optional[tuple[int, int]]:
    """``(x_left, x_right)`` of the mask's single run on ``row``; None if it is not one run."""
    xs = np.flatnonzero(mask[row])
    if len(xs) == 0 or xs[-1] - xs[0] + 1 != len(xs):
        return None
    return int(xs[0]), int(xs[-1])


def outline_row(mask: np.ndarray, min_width_px: float = MIN_WIDTH_PX) -> Optional[tuple[int, int, int]]:
    """Where to paint on an outline: ``(row, x_left, x_right)`` or None.

    Parameters
    ----------
    mask : (H, W) bool, one outlined trunk.

    The first row of :data:`ROW_FRACTIONS` where the outline is one run at least ``min_width_px``
    wide, and one run within 15 % of that width on the rows up to one width (at most 30 px) above
    and below.

    Examples
    --------
    >>> m = np.zeros((100, 60), bool); m[10:90, 20:45] = True
    >>> outline_row(m)
    (57, 20, 44)
    """
    ys = np.flatnonzero(mask.any(1))
    if len(ys) == 0:
        return None
    for f in ROW_FRACTIONS:
        y = int(ys[0] + f * (ys[-1] - ys[0]))
        r = run_width(mask, y)
        if r is None or r[1] - r[0] + 1 < min_width_px:
            continue
        w = r[1] - r[0] + 1
        reach = min(w, 30)
        ok = True
        for yy in range(max(0, y - reach), min(mask.shape[0], y + reach + 1), max(1, reach // 5)):
            q = run_width(mask, yy)
            if q is None or abs((q[1] - q[0] + 1) - w) > 0.15 * w:
                ok = False
                break
        if ok:
            return y, r[0], r[1]
    return None


def line_run(mask: np.ndarray, center_xy, direction, step: float = 0.25) -> Optional[float]:
    """Length (pixels) of the mask's run along the line through ``center_xy`` (2,) in
    ``direction`` (2,) that contains the centre; None when the centre is off the mask."""
    H, W = mask.shape
    d = np.asarray(direction, np.float64)
    d = d / (np.linalg.norm(d) + 1e-12)
    c = np.asarray(center_xy, np.float64)
    s = np.arange(-max(H, W), max(H, W), step)
    p = c[None] + s[:, None] * d[None]
    xi, yi = np.round(p[:, 0]).astype(int), np.round(p[:, 1]).astype(int)
    inside = (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
    on = np.zeros(len(s), bool)
    on[inside] = mask[yi[inside], xi[inside]]
    k = int(np.argmin(np.abs(s)))
    if not on[k]:
        return None
    lo, hi = k, k
    while lo > 0 and on[lo - 1]:
        lo -= 1
    while hi < len(s) - 1 and on[hi + 1]:
        hi += 1
    return float((hi - lo + 1) * step)


def run(folder: Path, out_dir: Path, outlines: dict, ratios=RATIOS, seed: int = 26, session=None,
        tap: bool = False) -> list[dict]:
    """Paint a rope across every wide outlined trunk at every ratio and measure; one dict each.
    ``tap``: the user taps the painted rope's middle (``dbh measure --pick``)."""
    from monodbh.calib import Camera, load_photo
    from monodbh.toolkit import pipeline as pl
    from monodbh.toolkit.frames import work_frame

    sess = session or pl.Session()
    rng = np.random.default_rng(seed)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for name, entry in sorted(outlines["photos"].items()):
        p = folder / name
        if not p.exists():
            continue
        rgb = load_photo(p)
        H, W = rgb.shape[:2]
        cam = Camera([[0.8 * W, 0, W / 2 - 0.5], [0, 0.8 * W, H / 2 - 0.5], [0, 0, 1]], np.zeros(5), (W, H))
        frame = work_frame(rgb, cam, sess.config.work_long_side_px)
        for k, tr in enumerate(entry["trunks"]):
            m = rasterize(tr["polygon"], (W, H))
            where = outline_row(m)
            if where is None:
                continue
            y0, xa, xb = where
            w = xb - xa + 1
            for ratio in ratios:
                T = max(1.2, ratio * w)
                sag = 0.06 * w * (1 if rng.random() < 0.5 else -1)
                q = out_dir / f"{p.stem}_t{k}_r{int(round(100 * ratio)):02d}.jpg"
                cv2.imwrite(str(q), cv2.cvtColor(paint_rope(rgb, y0, xa, xb, T, sag, rng), cv2.COLOR_RGB2BGR),
                            [cv2.IMWRITE_JPEG_QUALITY, 90])
                pick = (0.5 * (xa + xb), y0 + sag) if tap else None
                r = pl.measure_photo(str(q), cam, session=sess, want_debug=True, pick_xy=pick)
                row = dict(photo=name, trunk=k, ratio=ratio, thickness_px=round(T, 2), row=y0,
                           outline_px=int(w), dbh_cm=r.dbh_cm, width_px=None, true_px=None, err_pct=None,
                           at_painted=None, error=None if not r.error else r.error.split(": ", 1)[-1],
                           flags=list(r.flags or []))
                exy = r.debug.get("edges_xy") if r.debug else None
                if exy is not None and r.rope_xy is not None:
                    L, R = (np.asarray(frame.to_photo(np.asarray(e, np.float64)), np.float64) for e in exy)
                    mid = 0.5 * (L + R)
                    row["at_painted"] = bool(xa - 3 <= mid[0] <= xb + 3 and abs(mid[1] - y0) <= abs(sag) + T + 4)
                    true = line_run(m, (0.5 * (xa + xb), y0 + sag), R - L)
                    if row["at_painted"] and true:
                        row["width_px"] = round(float(np.linalg.norm(R - L)), 2)
                        row["true_px"] = round(true, 2)
                        row["err_pct"] = round(100 * (row["width_px"] / true - 1), 2)
                rows.append(row)
                print(json.dumps(row), file=sys.stderr, flush=True)
    return rows


def summarise(rows: list[dict]) -> dict:
    """Counts and the width error (median / 90th percentile / mean of |error|, share within 5 and
    10 %) over the rows measured at the painted rope."""
    e = np.array([abs(r["err_pct"]) for r in rows if r["err_pct"] is not None])
    out = dict(painted=len(rows), measured=int(len(e)),
               elsewhere=sum(1 for r in rows if r["at_painted"] is False),
               not_measured=sum(1 for r in rows if r["dbh_cm"] is None))
    if len(e):
        out.update(median_pct=float(np.median(e)), p90_pct=float(np.percentile(e, 90)), mean_pct=float(e.mean()),
                   within5=float((e <= 5).mean()), within10=float((e <= 10).mean()))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m monodbh.toolkit.evaluation.real_width_bench",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("folder", type=Path, help="the real photos (../shared/data/real_trees)")
    ap.add_argument("--out-dir", type=Path, default=Path("runs/real_width"), help="painted photos and rows.json")
    ap.add_argument("--outlines", type=Path, default=OUTLINES)
    ap.add_argument("--seed", type=int, default=26)
    ap.add_argument("--models-dir", type=Path, help="networks other than the shipped ones (a models folder)")
    ap.add_argument("--tap", action="store_true", help="tap the painted rope's middle (dbh measure --pick)")
    a = ap.parse_args(argv)
    if not a.folder.is_dir():
        print(f"error: {a.folder}: not a folder", file=sys.stderr)
        return 2
    session = None
    if a.models_dir is not None:
        from monodbh.toolkit.pipeline import Session
        session = Session(a.models_dir)
    rows = run(a.folder, a.out_dir, load_outlines(a.outlines), seed=a.seed, session=session, tap=a.tap)
    (a.out_dir / "rows.json").write_text(json.dumps(rows, indent=1))
    from rich.console import Console
    from rich.table import Table
    t = Table(title="stem width at a rope painted across the outlined trunks of the real photos")
    for c in ("painted rope", "painted", "measured there", "rope taken elsewhere", "width |error| median / p90",
              "within 5 % / 10 %"):
        t.add_column(c, justify="right")
    for ratio in list(RATIOS) + [None]:
        s = summarise([r for r in rows if ratio is None or r["ratio"] == ratio])
        t.add_row("all" if ratio is None else f"{ratio:.2f} x width", str(s["painted"]), str(s["measured"]),
                  str(s["elsewhere"]),
                  f"{s['median_pct']:.1f} / {s['p90_pct']:.1f} %" if s["measured"] else "-",
                  f"{100 * s['within5']:.0f} / {100 * s['within10']:.0f} %" if s["measured"] else "-")
    Console().print(t)
    return 0


if __name__ == "__main__":
    sys.exit(main())
