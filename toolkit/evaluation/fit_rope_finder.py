"""Calibration of the rope finder's acceptance rule on synthetic folders (a command, not used by ``dbh measure``).

Runs the rope finder (``monodbh.models.runtime.rope_finder``) on the pipeline's own working image of
every photo of ``dbh synth`` folders and writes, per photo, its best components with a label:
does the component lie on the true rope (its centre within ``max(6, 0.25 * length)`` px of a
visible rope pixel, the true rope mask undistorted like the photo)?

    python -m monodbh.toolkit.evaluation.fit_rope_finder data/calset data/calset2 --out runs/finder_cal.json
    python -m monodbh.toolkit.evaluation.fit_rope_finder --report runs/finder_cal.json [--failed EM.json]

``--report`` prints, for a grid of thresholds on the best component's ``peak`` and ``mass``, how
many rope-free photos would get a rope (must be 0), how many roped photos get the right rope
and how many a wrong one; ``--failed`` (rows of ``monodbh.toolkit.evaluation.error_model --json``) restricts
the roped photos to those the pipeline did not measure without the finder.

Imported by nothing (a command); imports the pipeline's working image, ``models.runtime.rope_finder``,
``toolkit.rope.finder`` and :mod:`.synth_samples`.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

__all__ = ["collect", "report"]


def _label(comp, rope_xy: np.ndarray) -> tuple[float, bool]:
    if not len(rope_xy):
        return float("inf"), False
    d = float(np.min(np.hypot(rope_xy[:, 0] - comp.center_xy[0], rope_xy[:, 1] - comp.center_xy[1])))
    return d, d <= max(6.0, 0.25 * comp.length_px)


def collect(folders: list[str], model: str | None = None, top: int = 5, limit: int | None = None) -> list[dict]:
    """Rows ``{folder, photo, roped, comps: [{peak, mass, n, length_px, thickness_px, dist_px, on_rope, ...}]}``."""
    import cv2

    from monodbh.models.runtime.rope_finder import RopeFinder
    from monodbh.toolkit.config import MeasureConfig
    from monodbh.toolkit.frames import work_frame

    from .synth_samples import camera_from_meta

    finder = RopeFinder(model)
    rows = []
    for folder in folders:
        for p in sorted(Path(folder).glob("*.jpg"))[:limit]:
            meta = json.loads(p.with_suffix(".json").read_text())
            rgb = cv2.imread(str(p))[..., ::-1]
            cam = camera_from_meta(meta)
            frame = work_frame(np.ascontiguousarray(rgb), cam, MeasureConfig().work_long_side_px)
            img, cw = frame.image, frame.camera_distorted
            with np.load(p.with_suffix(".npz")) as z:
                rope = z["rope"].astype(np.uint8) * 255
            if rope.shape != img.shape[:2]:
                rope = cv2.resize(rope, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_AREA)
            if np.any(np.asarray(cw.dist) != 0):
                rope, _ = cw.undistort_image(rope, alpha=0.0)
            ys, xs = np.nonzero(rope > 40)
            rope_xy = np.stack([xs, ys], 1).astype(np.float64)
            t = time.perf_counter()
            comps = finder.components(img)[:top]
            ms = 1000 * (time.perf_counter() - t)
            out = []
            for c in comps:
                d, ok = _label(c, rope_xy)
                out.append(dict(peak=round(c.peak, 3), mass=round(c.mass, 2), n=c.n, length_px=round(c.length_px, 1),
                                thickness_px=round(c.thickness_px, 2), center_xy=[round(v, 1) for v in c.center_xy],
                                direction=[round(v, 3) for v in c.direction], dist_px=round(d, 1), on_rope=ok))
            rows.append(dict(folder=str(folder), photo=p.stem, roped=bool(len(rope_xy)), ms=round(ms, 1), comps=out))
        print(f"{folder}: {sum(r['folder'] == str(folder) for r in rows)} photos", file=sys.stderr, flush=True)
    return rows


def _failed_set(em_path: str, folders: list[str]) -> set[tuple[str, str]]:
    """(folder, photo) of roped photos the pipeline did not measure, from error-model rows in folder order."""
    em = json.loads(Path(em_path).read_text())["rows"]
    roped = []
    for f in folders:
        for p in sorted(Path(f).glob("*.json")):
            m = json.loads(p.read_text())
            if m.get("roped_tree") and m.get("rope"):
                roped.append((f, p.stem))
    out = set()
    for (f, s), r in zip(roped, em):
        if r["photo"] != s:
            raise ValueError(f"{em_path}: rows out of step with {f} ({r['photo']} vs {s})")
        if r.get("dbh_cm") is None:
            out.add((f, s))
    return out


def report(rows: list[dict], failed: set | None = None) -> None:
    """Print the acceptance table (see the module docstring), with the rule of
    :mod:`monodbh.toolkit.rope.finder`."""
    from types import SimpleNamespace

    from monodbh.toolkit.rope.finder import rope_from_finder

    free = [r for r in rows if not r["roped"]]
    roped = [r for r in rows if r["roped"] and (failed is None or (r["folder"], r["photo"]) in failed)]
    print(f"rope-free {len(free)}, roped {len(roped)}" + (" (not measured without the finder)" if failed else ""))
    print(f"{'peak':>5} {'mass':>5} {'rival':>5} | free accepted | roped right | roped wrong | ambiguous")

    def comps(r):
        return [SimpleNamespace(**{**c, "polyline": np.array([c["center_xy"], c["center_xy"]], np.float32)})
                for c in r["comps"]]

    for pk in (3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 10.0):
        for ms in (6.0, 10.0, 20.0):
            for rv in (0.3, 0.5):
                fa = right = wrong = amb = 0
                for r in free + roped:
                    cs = comps(r)
                    det = rope_from_finder(cs, (4000, 4000), min_peak=pk, min_mass=ms, rival_share=rv)
                    amb += int(det.ambiguous)
                    if not det:
                        continue
                    c = next(c for c in cs if c.center_xy == det.center_xy)
                    if not r["roped"]:
                        fa += 1
                    elif c.on_rope:
                        right += 1
                    else:
                        wrong += 1
                print(f"{pk:5.1f} {ms:5.1f} {rv:5.1f} | {fa:13d} | {right:11d} | {wrong:11d} | {amb:9d}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m monodbh.toolkit.evaluation.fit_rope_finder",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("folders", nargs="*")
    ap.add_argument("--out")
    ap.add_argument("--model")
    ap.add_argument("--limit", type=int)
    ap.add_argument("--report")
    ap.add_argument("--failed")
    a = ap.parse_args(argv)
    if a.report:
        rows = json.loads(Path(a.report).read_text())
        folders = list(dict.fromkeys(r["folder"] for r in rows))
        report(rows, _failed_set(a.failed, folders) if a.failed else None)
        return 0
    rows = collect(a.folders, a.model, limit=a.limit)
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(rows))
    report(rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
