"""Synthetic benchmark of :func:`monodbh.toolkit.rope.detect_rope` (not on the measuring path).

Renders (once) ``count`` samples of dataset ``seed`` with the scene generator, caches the pixels
and the ground truth the benchmark needs as ``.npz`` files, then runs the detector on every cached
sample and prints detection / false-positive rates per scene kind and timings.

Run ``python -m monodbh.toolkit.bench_rope --help``. Rendering 150 samples at 1280x960 takes about
8-15 minutes on one loaded core; run it under ``nice``. The generator is imported lazily, only to
fill the cache (it needs the ``synth`` extra).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

__all__ = ["cache_samples", "load_sample", "evaluate_sample", "run_benchmark", "main"]

DEFAULT_CACHE = Path("/tmp/ropecache")


def _path(cache: Path, seed: int, index: int, size: tuple[int, int]) -> Path:
    return Path(cache) / f"s{seed}_{size[0]}x{size[1]}_{index:05d}.npz"


def cache_samples(seed: int, count: int, size: tuple[int, int] = (1280, 960), cache: Path = DEFAULT_CACHE,
                  *, start: int = 0, verbose: bool = True) -> list[Path]:
    """Render the samples that are not cached yet; return the ``count`` cache paths.

    Each ``.npz`` holds ``rgb`` (H, W, 3) uint8, ``rope`` (H, W) bool, ``instance`` (H, W) uint16,
    ``semantic`` (H, W) uint8 and ``meta`` (JSON string).
    """
    cache = Path(cache)
    cache.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(start, start + count):
        p = _path(cache, seed, i, size)
        paths.append(p)
        if p.exists():
            continue
        from monodbh.models.synthetic import generate_sample   # benchmark only
        t0 = time.perf_counter()
        s = generate_sample(seed, i, size)
        tmp = p.with_suffix(".tmp.npz")
        np.savez_compressed(tmp, rgb=s["rgb"], rope=s["rope"], instance=s["instance"].astype(np.uint16),
                            semantic=s["semantic"].astype(np.uint8), meta=json.dumps(s["meta"]))
        os.replace(tmp, p)
        if verbose:
            print(f"rendered {p.name} in {time.perf_counter() - t0:.1f}s", flush=True)
    return paths


def load_sample(path: Path) -> dict:
    """Load one cached sample (see :func:`cache_samples`)."""
    with np.load(path) as z:
        d = {k: z[k] for k in ("rgb", "rope", "instance", "semantic")}
        d["meta"] = json.loads(str(z["meta"]))
    return d


def _trunk_width_px(instance: np.ndarray, tree: int, y: float) -> float:
    """Width in pixels of tree ``tree`` in the rows around ``y`` (median run length)."""
    H = instance.shape[0]
    y = int(round(y))
    ws = []
    for yy in range(max(0, y - 3), min(H, y + 4)):
        row = instance[yy] == tree
        if row.any():
            xs = np.flatnonzero(row)
            ws.append(xs[-1] - xs[0] + 1)
    return float(np.median(ws)) if ws else 0.0


def _rope_thickness_px(rope: np.ndarray) -> float:
    """Mean thickness of a GT rope mask: area / skeleton length."""
    from skimage.morphology import skeletonize
    if not rope.any():
        return 0.0
    sk = skeletonize(rope)
    return float(rope.sum() / max(1, sk.sum()))


def evaluate_sample(d: dict, det) -> dict:
    """Score one detection against the ground truth of sample ``d``.

    Returns a dict with ``roped`` (bool), ``hit`` (detection on the GT rope of the roped tree),
    ``found``, ``ambiguous``, ``err_px`` (centre distance to the nearest GT rope pixel on the roped
    tree), ``tol_px``, ``thick_px`` (GT rope thickness), ``kinds`` (distractor kinds).
    """
    meta = d["meta"]
    kinds = sorted({x["kind"] for x in meta.get("distractors", [])})
    out = dict(roped=meta.get("roped_tree") is not None, found=bool(det.found), ambiguous=bool(det.ambiguous),
               hit=False, err_px=float("nan"), tol_px=float("nan"), thick_px=float("nan"), kinds=kinds,
               visible=0)
    if out["roped"]:
        tree = int(meta["roped_tree"])
        m = d["rope"] & (d["instance"] == tree)
        out["visible"] = int(m.sum())
        if m.any():
            ys, xs = np.nonzero(m)
            out["thick_px"] = _rope_thickness_px(m)
            yc = float(np.median(ys))
            tw = _trunk_width_px(d["instance"], tree, yc)
            out["tol_px"] = max(5.0, 0.5 * tw)
            if det.found:
                cx, cy = det.center_xy
                e = float(np.min(np.hypot(xs - cx, ys - cy)))
                out["err_px"] = e
                out["hit"] = e <= out["tol_px"]
    return out


def run_benchmark(paths: list[Path], *, verbose: bool = False, **detect_kw) -> list[dict]:
    """Detect on every cached sample; return one record per sample (see :func:`evaluate_sample`)."""
    from monodbh.toolkit.rope import detect_rope
    recs = []
    for p in paths:
        d = load_sample(p)
        t0 = time.perf_counter()
        det = detect_rope(d["rgb"], **detect_kw)
        dt = time.perf_counter() - t0
        r = evaluate_sample(d, det)
        r.update(name=p.name, time_ms=1000 * dt, reason=det.reason,
                 center=None if det.center_xy is None else [float(v) for v in det.center_xy])
        recs.append(r)
        if verbose:
            print(f"{p.name}: roped={r['roped']} found={r['found']} hit={r['hit']} err={r['err_px']:.1f} "
                  f"tol={r['tol_px']:.1f} thick={r['thick_px']:.1f} kinds={r['kinds']} {dt*1000:.0f}ms "
                  f"{det.reason}", flush=True)
    return recs


def summarize(recs: list[dict]) -> str:
    """Markdown table of the benchmark records."""
    def rate(sel, key):
        n = len(sel)
        k = sum(bool(r[key]) for r in sel)
        return f"{k}/{n} ({100 * k / n:.1f} %)" if n else "-"

    roped = [r for r in recs if r["roped"] and r["visible"] > 0]
    lines = ["| subset | n | metric | value |", "|---|---|---|---|"]
    lines.append(f"| roped (rope visible) | {len(roped)} | detected (centre on GT rope) | {rate(roped, 'hit')} |")
    thin = [r for r in roped if r["thick_px"] < 2.0]
    lines.append(f"| roped, thin (< 2 px) | {len(thin)} | detected | {rate(thin, 'hit')} |")
    amb = [r for r in roped if r["ambiguous"]]
    lines.append(f"| roped | {len(roped)} | ambiguous (not found) | {len(amb)} |")
    wrong = [r for r in roped if r["found"] and not r["hit"]]
    lines.append(f"| roped | {len(roped)} | found but wrong place | {len(wrong)} |")
    none = [r for r in recs if not r["roped"]]
    lines.append(f"| no rope | {len(none)} | found=False (correct) | "
                 f"{sum(not r['found'] for r in none)}/{len(none)} |")
    for k in ("flagging_tape", "paint_mark", "second_rope", "red_leaves", "red_jacket"):
        sel = [r for r in recs if k in r["kinds"]]
        selr = [r for r in sel if r["roped"] and r["visible"] > 0]
        seln = [r for r in sel if not r["roped"]]
        lines.append(f"| with {k} | {len(sel)} | roped hit / no-rope false positives | "
                     f"{rate(selr, 'hit')} / {sum(r['found'] for r in seln)}/{len(seln)} |")
    t = np.array([r["time_ms"] for r in recs])
    if len(t):
        lines.append(f"| all | {len(recs)} | time ms (median / max) | {np.median(t):.0f} / {t.max():.0f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m monodbh.toolkit.bench_rope", description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=7000)
    ap.add_argument("--count", type=int, default=150)
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--size", default="1280x960", help="WxH")
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    ap.add_argument("--render-only", action="store_true", help="only fill the cache")
    ap.add_argument("--cached-only", action="store_true", help="evaluate only samples already cached")
    ap.add_argument("--json", type=Path, help="write the per-sample records here")
    ap.add_argument("-v", "--verbose", action="store_true")
    a = ap.parse_args(argv)
    W, H = (int(v) for v in a.size.lower().split("x"))
    if a.cached_only:
        paths = [p for i in range(a.start, a.start + a.count)
                 if (p := _path(a.cache, a.seed, i, (W, H))).exists()]
    else:
        paths = cache_samples(a.seed, a.count, (W, H), a.cache, start=a.start)
    if a.render_only:
        return 0
    recs = run_benchmark(paths, verbose=a.verbose)
    if a.json:
        a.json.write_text(json.dumps(recs, indent=1))
    print(summarize(recs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
