"""Synthetic benchmark of :func:`monodbh.toolkit.rope.detect_rope` (not on the measuring path).

Renders (once) ``count`` samples of dataset ``seed`` with the scene generator, caches the pixels
and the ground truth the benchmark needs as ``.npz`` files, then runs the detector on every cached
sample and prints detection / false-positive rates per scene kind and timings. ``--fit`` refits
:data:`monodbh.toolkit.rope.SCORE_WEIGHTS` (2-fold cross-validated report, then weights on all).

Typical use (rendering 150 samples at 1280x960 takes 10-25 minutes on a shared 2-core machine;
run it under ``nice``; the generator needs the ``synth`` extra and is imported lazily)::

    nice python -m monodbh.toolkit.evaluation.rope_bench --render-only --extra-no-rope 36
    python -m monodbh.toolkit.evaluation.rope_bench --cached-only --extra-no-rope 36
    python -m monodbh.toolkit.evaluation.rope_bench --cached-only --extra-no-rope 36 --fit \
        --real-negatives /work/shared/data/real_trees

A sample counts as detected when the reported centre lies within max(5 px, half the roped
trunk's width) of a GT rope pixel of the roped tree.

Imported by nothing (a command); imports ``toolkit.rope``, the scene generator and
``toolkit.outputs.atomic``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from monodbh.toolkit.outputs.atomic import atomic_open

__all__ = ["cache_samples", "load_sample", "evaluate_sample", "run_benchmark", "summarize", "no_rope_indices",
           "oracle_height_check", "collect_candidates", "collect_real_negatives", "count_flagged",
           "fit_score_weights", "main"]

DEFAULT_CACHE = Path("/tmp/ropecache")


def _path(cache: Path, seed: int, index: int, size: tuple[int, int]) -> Path:
    return Path(cache) / f"s{seed}_{size[0]}x{size[1]}_{index:05d}.npz"


def no_rope_indices(seed: int, count: int, start: int) -> list[int]:
    """The first ``count`` sample indices >= ``start`` of dataset ``seed`` without a rope (the
    scene is sampled, not rendered, to tell)."""
    from monodbh.models.synthetic import sample_seed
    from monodbh.models.synthetic.scene import sample_scene
    out, i = [], start
    while len(out) < count:
        s = sample_seed(seed, i)
        if sample_scene(np.random.default_rng(s), 64, 48, seed=s).roped_tree is None:
            out.append(i)
        i += 1
    return out


def cache_samples(seed: int, count: int, size: tuple[int, int] = (1280, 960), cache: Path = DEFAULT_CACHE,
                  *, start: int = 0, indices: list[int] | None = None, verbose: bool = True) -> list[Path]:
    """Render the samples that are not cached yet; return the ``count`` cache paths.

    Each ``.npz`` holds ``rgb`` (H, W, 3) uint8, ``rope`` (H, W) bool, ``instance`` (H, W) uint16,
    ``semantic`` (H, W) uint8 and ``meta`` (JSON string).
    """
    cache = Path(cache)
    cache.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in (list(range(start, start + count)) if indices is None else indices):
        p = _path(cache, seed, i, size)
        paths.append(p)
        if p.exists():
            continue
        from monodbh.models.synthetic import generate_sample   # benchmark only
        t0 = time.perf_counter()
        s = generate_sample(seed, i, size)
        with atomic_open(p, "wb") as f:
            np.savez_compressed(f, rgb=s["rgb"], rope=s["rope"], instance=s["instance"].astype(np.uint16),
                                semantic=s["semantic"].astype(np.uint8), meta=json.dumps(s["meta"]))
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
               visible=0, gt_contrast=float("nan"), det_thick_px=float(det.thickness_px) if det.found else float("nan"))
    if out["roped"]:
        tree = int(meta["roped_tree"])
        m = d["rope"] & (d["instance"] == tree)
        out["visible"] = int(m.sum())
        if m.any():
            ys, xs = np.nonzero(m)
            out["thick_px"] = _rope_thickness_px(m)
            out["gt_contrast"] = _rope_contrast(d["rgb"], m, d["instance"] == tree)
            yc = float(np.median(ys))
            tw = _trunk_width_px(d["instance"], tree, yc)
            out["tol_px"] = max(5.0, 0.5 * tw)
            if det.found:
                cx, cy = det.center_xy
                e = float(np.min(np.hypot(xs - cx, ys - cy)))
                out["err_px"] = e
                out["hit"] = e <= out["tol_px"]
    return out


def _rope_contrast(rgb: np.ndarray, rope: np.ndarray, tree: np.ndarray) -> float:
    """How visible the GT rope is: mean red-ness on it minus the median on the bark around it."""
    import cv2
    from monodbh.toolkit.rope import redness_map
    F = redness_map(rgb)
    near = cv2.dilate(rope.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    core = cv2.dilate(rope.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    ring = near & ~core & tree
    bg = float(np.median(F[ring])) if ring.any() else 0.0
    return float(F[rope].mean() - bg)


def oracle_height_check(d: dict):
    """A stand-in for the pipeline's ``height_check``: rejects candidates centred on a tree that
    carries a flagging tape (at 0.3-0.8 m or 1.9-2.6 m in the generator) unless they touch the GT
    rope. Uses the ground truth; for the benchmark only."""
    tapes = {x["tree"] for x in d["meta"].get("distractors", []) if x["kind"] == "flagging_tape"}
    inst, rope = d["instance"], d["rope"]
    H, W = inst.shape

    def check(c) -> bool:
        x = int(min(max(round(c.center_xy[0]), 0), W - 1))
        y = int(min(max(round(c.center_xy[1]), 0), H - 1))
        if int(inst[y, x]) not in tapes:
            return True
        return bool(rope[max(0, y - 4):y + 5, max(0, x - 4):x + 5].any())
    return check


def run_benchmark(paths: list[Path], *, verbose: bool = False, tree_mask: str | None = None,
                  oracle_height: bool = False, **detect_kw) -> list[dict]:
    """Detect on every cached sample; return one record per sample (see :func:`evaluate_sample`).

    ``tree_mask="gt"`` passes the ground-truth tree pixels (semantic class 3) as ``tree_mask``
    (an upper bound for a pipeline that passes its segmenter's tree mask); ``oracle_height``
    passes :func:`oracle_height_check` as ``height_check``.
    ``time_ms`` is wall time, ``cpu_ms`` the process CPU time (OpenCV set to one thread).
    """
    import cv2
    from monodbh.toolkit.rope import detect_rope
    cv2.setNumThreads(1)
    recs = []
    for p in paths:
        d = load_sample(p)
        tm = (d["semantic"] == 3) if tree_mask == "gt" else None
        t0 = time.perf_counter()
        c0 = time.process_time()
        kw = dict(detect_kw)
        if oracle_height:
            kw["height_check"] = oracle_height_check(d)
        det = detect_rope(d["rgb"], tm, **kw)
        cpu = time.process_time() - c0
        dt = time.perf_counter() - t0
        r = evaluate_sample(d, det)
        r.update(name=p.name, time_ms=1000 * dt, cpu_ms=1000 * cpu, reason=det.reason,
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
    for lo, hi in ((-1.0, 0.02), (0.02, 0.05), (0.05, 9.0)):
        sel = [r for r in roped if lo <= r["gt_contrast"] < hi]
        lines.append(f"| roped, GT rope red-ness contrast in [{max(lo, 0):.2f}, {hi if hi < 9 else 'inf'}) | "
                     f"{len(sel)} | detected | {rate(sel, 'hit')} |")
    hits = [r for r in roped if r["hit"]]
    if hits:
        e = np.array([r["det_thick_px"] - r["thick_px"] for r in hits])
        lines.append(f"| roped, detected | {len(hits)} | thickness error px (median / median abs) | "
                     f"{np.median(e):+.2f} / {np.median(np.abs(e)):.2f} |")
        ce = np.array([r["err_px"] for r in hits])
        lines.append(f"| roped, detected | {len(hits)} | centre to GT rope px (median / p90) | "
                     f"{np.median(ce):.1f} / {np.percentile(ce, 90):.1f} |")
    t = np.array([r["time_ms"] for r in recs])
    c = np.array([r.get("cpu_ms", np.nan) for r in recs])
    if len(t):
        lines.append(f"| all | {len(recs)} | wall ms (median / max) | {np.median(t):.0f} / {t.max():.0f} |")
        lines.append(f"| all | {len(recs)} | CPU ms, 1 thread (median / max) | {np.median(c):.0f} / {np.max(c):.0f} |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- score fitting

def collect_candidates(paths: list[Path]) -> list[dict]:
    """Per sample: every scored candidate's features and whether it lies on the GT rope.

    Returns one dict per sample: ``name``, ``roped``, ``visible``, ``cands`` (list of
    ``{"f": features, "lab": bool, "length_px": float, "tape": bool}``; ``tape``: on a tree that
    carries a flagging tape, see :func:`oracle_height_check`).
    """
    from monodbh.toolkit.rope import detect_rope
    out = []
    for p in paths:
        d = load_sample(p)
        meta = d["meta"]
        det = detect_rope(d["rgb"], min_score=-1e9, ambiguity_margin=-1.0)
        gt = d["rope"] & (d["instance"] == (meta["roped_tree"] or -1))
        cands = []
        if gt.any():
            ys, xs = np.nonzero(gt)
            tol = max(5.0, 0.5 * _trunk_width_px(d["instance"], meta["roped_tree"], float(np.median(ys))))
        on_tape = oracle_height_check(d)
        for c in det.candidates:
            lab = bool(gt.any() and np.min(np.hypot(xs - c.center_xy[0], ys - c.center_xy[1])) <= tol)
            cands.append(dict(f=c.features, lab=lab, length_px=c.length_px, tape=not on_tape(c)))
        out.append(dict(name=p.name, roped=meta["roped_tree"] is not None, visible=bool(gt.any()), cands=cands))
    return out


def collect_real_negatives(folder: Path) -> list[dict]:
    """Candidates on real photos known to have no rope (e.g. ``/work/shared/data/real_trees``), as
    no-rope samples for :func:`fit_score_weights` (real bark, twigs and foliage; the renderer's are
    simpler)."""
    import cv2
    from monodbh.toolkit.rope import detect_rope
    out = []
    for p in sorted(Path(folder).glob("*.jpg")):
        rgb = cv2.imread(str(p), cv2.IMREAD_COLOR)[:, :, ::-1].copy()
        det = detect_rope(rgb, min_score=-1e9, ambiguity_margin=-1.0)
        out.append(dict(name=p.name, path=str(p), roped=False, visible=False,
                        cands=[dict(f=c.features, lab=False, length_px=c.length_px, tape=False)
                               for c in det.candidates]))
    return out


def count_flagged(photos: list[str], **detect_kw) -> int:
    """How many of the (rope-free) photos get a rope or an ambiguity from :func:`detect_rope`."""
    import cv2
    from monodbh.toolkit.rope import detect_rope
    n = 0
    for p in photos:
        det = detect_rope(cv2.imread(str(p), cv2.IMREAD_COLOR)[:, :, ::-1].copy(), **detect_kw)
        n += bool(det.found or det.ambiguous)
    return n


def fit_score_weights(samples: list[dict], *, max_fp_rate: float = 0.1, l2: float = 0.03,
                      iters: int = 3000, lr: float = 0.3, ignore_tape: bool = True) -> dict:
    """Fit the log-odds weights of :data:`monodbh.toolkit.rope.SCORE_WEIGHTS`.

    Pointwise logistic loss (the GT candidate of each roped sample against all other candidates,
    which are down-weighted per sample) plus a pairwise ranking loss (GT above every other
    candidate of its photo), L2-regularised on standardised features. The bias is then set so
    that at most ``max_fp_rate`` of the no-rope samples have a candidate scoring above 0; with
    ``ignore_tape`` candidates on flagging-taped trees are left out of that count (a tape looks
    like a rope; telling them apart is the pipeline's ``height_check``).
    """
    keys = [k for k in samples[0]["cands"][0]["f"]] if samples and samples[0]["cands"] else None
    for s in samples:
        if s["cands"]:
            keys = list(s["cands"][0]["f"])
            break
    X, y, wt, P = [], [], [], []
    for s in samples:
        cs = [c for c in s["cands"] if c["f"]["shape"] > 0]
        pos = [c for c in cs if c["lab"]]
        neg = [c for c in cs if not c["lab"]]
        phi = lambda c: [c["f"][k] for k in keys]
        if pos:
            X.append(phi(pos[0])); y.append(1.0); wt.append(1.0)
            P += [np.subtract(phi(pos[0]), phi(q)) for q in neg]
        for q in neg:
            X.append(phi(q)); y.append(0.0); wt.append(3.0 / max(1, len(neg)))
    X, y, wt, P = np.array(X), np.array(y), np.array(wt), np.array(P)
    mu, sd = X.mean(0), X.std(0) + 1e-6
    Z, PZ = (X - mu) / sd, P / sd
    w, b = np.zeros(len(keys)), 0.0
    for _ in range(iters):
        p = 1.0 / (1.0 + np.exp(-np.clip(Z @ w + b, -30, 30)))
        g = (wt * (p - y)) @ Z / wt.sum()
        gb = float((wt * (p - y)).sum() / wt.sum())
        gr = -(PZ * (1.0 / (1.0 + np.exp(np.clip(PZ @ w, -30, 30))))[:, None]).mean(0) if len(PZ) else 0.0
        w -= lr * (g + gr + l2 * w)
        b -= lr * gb
    W = w / sd
    B = b - float((mu / sd) @ w)
    tops = [max([float(np.dot(W, [c["f"][k] for k in keys])) + B for c in s["cands"]
                 if c["f"]["shape"] > 0 and not (ignore_tape and c.get("tape"))],
                default=-np.inf) for s in samples if not s["roped"]]
    if tops:
        B -= float(np.quantile(tops, 1.0 - max_fp_rate))
    out = {"bias": round(B, 3)}
    out.update({k: round(float(v), 3) for k, v in zip(keys, W)})
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m monodbh.toolkit.evaluation.rope_bench", description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=7000)
    ap.add_argument("--count", type=int, default=150)
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--size", default="1280x960", help="WxH")
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    ap.add_argument("--extra-no-rope", type=int, default=0, metavar="N",
                    help="also use the first N no-rope samples after the range (better false-positive estimate)")
    ap.add_argument("--render-only", action="store_true", help="only fill the cache")
    ap.add_argument("--cached-only", action="store_true", help="evaluate only samples already cached")
    ap.add_argument("--json", type=Path, help="write the per-sample records here")
    ap.add_argument("--tree-mask", choices=["gt"], help="pass the GT tree pixels as tree_mask")
    ap.add_argument("--oracle-height", action="store_true",
                    help="pass a GT-based height_check that rejects bands on flagging-taped trees")
    ap.add_argument("--fit", action="store_true",
                    help="fit SCORE_WEIGHTS on the samples (2-fold cross-validated report, then all)")
    ap.add_argument("--real-negatives", type=Path, metavar="DIR",
                    help="with --fit: rope-free real photos (*.jpg) used as extra negatives (cross-validated)")
    ap.add_argument("-v", "--verbose", action="store_true")
    a = ap.parse_args(argv)
    W, H = (int(v) for v in a.size.lower().split("x"))
    extra = no_rope_indices(a.seed, a.extra_no_rope, a.start + a.count) if a.extra_no_rope else []
    idx = list(range(a.start, a.start + a.count)) + extra
    if a.cached_only:
        paths = [p for i in idx if (p := _path(a.cache, a.seed, i, (W, H))).exists()]
    else:
        paths = cache_samples(a.seed, len(idx), (W, H), a.cache, indices=idx)
    if a.render_only:
        return 0
    if a.fit:
        return _fit_report(paths, a)
    recs = run_benchmark(paths, verbose=a.verbose, tree_mask=a.tree_mask, oracle_height=a.oracle_height)
    if a.json:
        a.json.write_text(json.dumps(recs, indent=1))
    print(summarize(recs))
    return 0


def _fit_report(paths: list[Path], a) -> int:
    samples = collect_candidates(paths)
    real = collect_real_negatives(a.real_negatives) if a.real_negatives else []
    halves = (paths[0::2], paths[1::2])
    rhalves = (real[0::2], real[1::2])
    for oracle in (False, True):
        recs, flagged = [], 0
        for k in (0, 1):
            train = {p.name for p in halves[k]}
            w = fit_score_weights([s for s in samples if s["name"] in train] + rhalves[k])
            recs += run_benchmark(halves[1 - k], tree_mask=a.tree_mask, weights=w, oracle_height=oracle)
            flagged += count_flagged([r["path"] for r in rhalves[1 - k]], weights=w)
        print(f"2-fold cross-validation (weights fitted on the other half){', oracle height check' if oracle else ''}:")
        print(summarize(recs))
        if real:
            print(f"| real rope-free photos (held-out half each) | {len(real)} | reported a rope or ambiguity | "
                  f"{flagged}/{len(real)} |")
    w = fit_score_weights(samples + real)
    print("fitted on all:")
    print("SCORE_WEIGHTS = dict(" + ", ".join(f"{k}={v}" for k, v in w.items()) + ")")
    return 0


if __name__ == "__main__":
    sys.exit(main())
