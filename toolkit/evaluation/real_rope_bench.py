"""Real photos with a painted rope: does ``dbh measure`` find a rope on real bark (not on the
measuring path; a benchmark command, imports the pipeline).

No real photo of a roped tree is at hand, and the rope detectors were tuned (the rope finder
trained) on synthetic scenes only. This check paints a red rope band across a trunk of each real
photo (``../shared/data/real_trees``, no rope in any) and measures the photo as a user would
(``measure_photo`` with a default camera, fx = 0.8 x width): the painted rope must be found where
it was painted, and nowhere else.

Painting (:func:`paint_rope`): the segmenter's largest stem-like instance (the mask one run across
the rows up to a stem width, at most 30 px, above and below, its width steady within 30 %) at 55 % of its visible
extent (else 65, 45, 75, 35 %); a band across its width, a shallow elliptic arc (sag 6 % of the
width, up or down: the band seen from a little above or below), ``thickness_px`` thick, deep red
(sRGB 175, 28, 24) shaded by the bark's own light in that row and darker at the stem's flanks
and the band's edges, anti-aliased (4x supersampled), blurred 0.6 px, with 2-level noise, saved
as JPEG quality 90. The thickness is a fraction of the stem's width (a 1 cm rope on stems of
8-25 cm is 0.04-0.12 of it; ropes are at least 1.2 px).

python -m monodbh.toolkit.evaluation.real_rope_bench ../shared/data/real_trees --out-dir runs/painted

Imported by nothing (a command); imports the pipeline (``Session``, ``measure_photo``) and
``monodbh.calib``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

__all__ = ["stem_row", "paint_rope", "painted_hit", "run", "main"]

#: rope thickness as a fraction of the stem's width in the photo (a 1 cm rope on 8-25 cm stems)
RATIOS = (0.04, 0.08, 0.12)
#: rows of the summary table (rope thickness, px)
THICKNESS_BINS = ((0.0, 2.0), (2.0, 4.0), (4.0, float("inf")))
#: sRGB colour of the painted rope where the bark is of median brightness
ROPE_RGB = (175.0, 28.0, 24.0)


def stem_row(instance: np.ndarray, max_candidates: int = 3):
    """Where to paint: ``(tree_id, row, x_left, x_right)`` on the largest stem-like instance, or None.

    Parameters
    ----------
    instance : (H, W) int
        Instance ids (0 = no tree).

    A row is stem-like when the instance is one run of pixels across it and across the rows up to
    one run-width (at most 30 px) above and below, each within 30 % of its width, and narrower than
    60 % of the photo.
    """
    H, W = instance.shape
    ids, cnt = np.unique(instance[instance > 0], return_counts=True)
    for tid in ids[np.argsort(-cnt)][:max_candidates]:
        m = instance == tid
        ys = np.nonzero(m.any(1))[0]
        for f in (0.55, 0.65, 0.45, 0.75, 0.35):
            y = int(ys.min() + f * (ys.max() - ys.min()))
            xs = np.nonzero(m[y])[0]
            if len(xs) < 8 or xs.max() - xs.min() + 1 > 1.2 * len(xs) or len(xs) >= 0.6 * W:
                continue
            w = len(xs)
            ok = True
            reach = min(w, 30)
            for yy in range(max(0, y - reach), min(H, y + reach + 1), max(1, reach // 4)):
                r = np.nonzero(m[yy])[0]
                if len(r) == 0 or r.max() - r.min() + 1 > 1.2 * len(r) or abs(len(r) - w) > 0.3 * w:
                    ok = False
                    break
            if ok:
                return int(tid), y, int(xs.min()), int(xs.max())
    return None


def paint_rope(rgb: np.ndarray, row: int, x_left: int, x_right: int, thickness_px: float, sag: float,
               rng: np.random.Generator) -> np.ndarray:
    """A red rope band painted across ``rgb`` between ``x_left`` and ``x_right`` at ``row``.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
    row, x_left, x_right : the band's middle row at the stem's edges and the stem's extent (px).
    thickness_px : the band's thickness.
    sag : the arc's depth at the stem's middle (px, + down).

    Returns
    -------
    (H, W, 3) uint8 : the painted photo.

    Examples
    --------
    >>> img = np.full((40, 60, 3), 120, np.uint8)
    >>> out = paint_rope(img, 20, 20, 39, 3.0, 0.0, np.random.default_rng(0))
    >>> bool(out[20, 30, 0] > 2 * out[20, 30, 1]), bool((out[5] == 120).all())
    (True, True)
    """
    H, W = rgb.shape[:2]
    img = rgb.astype(np.float32)
    w = x_right - x_left + 1
    xc = 0.5 * (x_left + x_right)
    luma = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    med = float(np.median(luma[row, x_left:x_right + 1])) + 1.0
    base = np.array(ROPE_RGB, np.float32)
    layer = np.zeros_like(img)
    alpha = np.zeros((H, W), np.float32)
    ss = 4
    T = float(thickness_px)
    for x in range(max(0, x_left), min(W, x_right + 1)):
        u = (x - xc) / (0.5 * w)
        arc = np.sqrt(max(0.0, 1.0 - u * u))
        yc = row + sag * arc
        shade = float(np.clip(luma[row, x] / med, 0.45, 1.3)) * (0.55 + 0.45 * arc)
        for yy in range(int(np.floor(yc - T / 2 - 1)), int(np.ceil(yc + T / 2 + 1)) + 1):
            if not 0 <= yy < H:
                continue
            d = ((yy - 0.5 + (np.arange(ss) + 0.5) / ss) - yc) / (T / 2)
            inside = np.abs(d) <= 1
            cover = float(inside.mean())
            if cover <= 0:
                continue
            prof = float(np.mean(np.where(inside, 0.7 + 0.3 * np.sqrt(np.clip(1 - d * d, 0, 1)), 0))) / cover
            layer[yy, x] = np.clip(base * shade * prof, 0, 255)
            alpha[yy, x] = cover
    alpha_b = cv2.GaussianBlur(alpha, (0, 0), 0.6)[..., None]
    support = cv2.GaussianBlur(np.ceil(alpha), (0, 0), 0.6)[..., None]
    lay = np.where(alpha_b > 1e-3, cv2.GaussianBlur(layer, (0, 0), 0.6) / np.maximum(support, 1e-3), 0)
    out = img * (1 - alpha_b) + lay * alpha_b + rng.normal(0, 2.0, img.shape).astype(np.float32) * alpha_b
    return np.clip(out, 0, 255).astype(np.uint8)


def painted_hit(rope_xy, row: int, x_left: int, x_right: int, thickness_px: float, sag: float) -> bool:
    """Is the reported rope centre on the painted band (within max(4 px, its thickness) of the
    arc, between the stem's edges give or take 3 px)?"""
    x, y = rope_xy
    w = x_right - x_left + 1
    u = (x - 0.5 * (x_left + x_right)) / (0.5 * w)
    y_arc = row + sag * np.sqrt(max(0.0, 1.0 - u * u))
    return bool(x_left - 3 <= x <= x_right + 3 and abs(y - y_arc) <= max(4.0, thickness_px))


def run(photos, out_dir: Path, ratios=RATIOS, seed: int = 16, session=None) -> list[dict]:
    """Paint and measure every photo at every ratio; one dict per painted photo (or per skipped one)."""
    from monodbh.calib import Camera, load_photo
    from monodbh.toolkit import pipeline as pl

    sess = session or pl.Session()
    rng = np.random.default_rng(seed)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for p in photos:
        rgb = load_photo(p)
        H, W = rgb.shape[:2]
        seg = sess.segmenter.predict(rgb, size=(W, H))
        where = stem_row(seg.instance)
        if where is None:
            rows.append(dict(photo=Path(p).name, painted=False))
            continue
        _, y0, xa, xb = where
        w = xb - xa + 1
        cam = Camera([[0.8 * W, 0, W / 2 - 0.5], [0, 0.8 * W, H / 2 - 0.5], [0, 0, 1]], np.zeros(5), (W, H))
        for ratio in ratios:
            T = max(1.2, ratio * w)
            sag = 0.06 * w * (1 if rng.random() < 0.5 else -1)
            q = out_dir / f"{Path(p).stem}_r{int(round(100 * ratio)):02d}.jpg"
            painted = paint_rope(rgb, y0, xa, xb, T, sag, rng)
            cv2.imwrite(str(q), cv2.cvtColor(painted, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 90])
            r = pl.measure_photo(str(q), cam, session=sess)
            hit = None if r.rope_xy is None else painted_hit(r.rope_xy, y0, xa, xb, T, sag)
            rows.append(dict(photo=Path(p).name, painted=True, ratio=ratio, thickness_px=round(T, 2), stem_px=int(w),
                             at=[int(round(0.5 * (xa + xb))), int(round(y0 + sag))],
                             rope_xy=None if r.rope_xy is None else [round(v, 1) for v in r.rope_xy],
                             hit=hit, dbh_cm=r.dbh_cm, dbh_sigma_cm=r.dbh_sigma_cm,
                             error=None if not r.error else r.error.split(": ", 1)[-1],
                             flags=list(r.flags or [])))
            print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    return rows


def _reason(err: str) -> str:
    if "runs out of the photo" in err:
        return "stem runs out of the photo"
    if "look like a rope to the rope finder" in err:
        return "refused by the rope finder's check"
    if "two rope candidates" in err:
        return "two rope candidates"
    if "no red rope found" in err:
        return "no rope found"
    return err[:60]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m monodbh.toolkit.evaluation.real_rope_bench", description=__doc__.split("\n")[0])
    ap.add_argument("folder", type=Path, help="real photos (*.jpg), no rope in them")
    ap.add_argument("--out-dir", type=Path, default=Path("runs/painted_rope"), help="painted photos and rows.json")
    ap.add_argument("--seed", type=int, default=16)
    a = ap.parse_args(argv)
    photos = sorted(a.folder.glob("*.jpg"))
    if not photos:
        print(f"error: {a.folder}: no *.jpg photos", file=sys.stderr)
        return 2
    rows = run(photos, a.out_dir, seed=a.seed)
    (a.out_dir / "rows.json").write_text(json.dumps(rows, indent=1))
    from rich.console import Console
    from rich.table import Table
    t = Table(title=f"painted ropes on {len(photos)} real photos ({sum(1 for r in rows if r['painted']) // len(RATIOS)} with a stem to paint on)")
    for c in ("rope thickness", "painted", "measured at the painted rope", "rope taken elsewhere",
              "not measured (why)"):
        t.add_column(c, justify="right" if c != "not measured (why)" else "left")
    for lo, hi in THICKNESS_BINS:
        s = [r for r in rows if r["painted"] and lo <= r["thickness_px"] < hi]
        reasons: dict[str, int] = {}
        for r in s:
            if r["dbh_cm"] is None and r["hit"] is not False:
                k = _reason(r["error"] or "")
                reasons[k] = reasons.get(k, 0) + 1
        t.add_row(f"{lo:g}-{hi:g} px" if np.isfinite(hi) else f">= {lo:g} px", str(len(s)),
                  str(sum(1 for r in s if r["hit"] and r["dbh_cm"] is not None)),
                  str(sum(1 for r in s if r["hit"] is False)),
                  ", ".join(f"{v} {k}" for k, v in sorted(reasons.items(), key=lambda kv: -kv[1])) or "-")
    Console().print(t)
    return 0


if __name__ == "__main__":
    sys.exit(main())
