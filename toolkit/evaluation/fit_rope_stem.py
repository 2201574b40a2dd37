"""Fit and check :data:`monodbh.toolkit.rope.config.StemSearchConfig.weights`, and cut the rope verifier's examples.

Collects every stem band (:func:`~monodbh.toolkit.rope.stem_search.stem_bands`) of the photos in
``dbh synth`` folders, labels it by the ground truth, fits the logistic weights (L2-damped
Newton) on the ``--fit`` folders, and prints photo-level results on every folder for a few
thresholds: where the band detector finds no rope, is the best trunk-like band the rope, a wrong
band, or nothing; on rope-free scenes and on ``--negatives`` (photo folders without a rope, e.g.
``/work/shared/data/real_trees``), does any band pass?

A band is on the rope when its middle lies within ``max(8, 0.2 w)`` rows and ``max(8, w)``
columns of the projected rope centre (``w``: the stem's width there; the ring's centre is
inside the stem, so near stems seen from above show the rope several rows lower).

The rope verifier's training examples (``dbh train rope_verifier``) are cut with ``--bank FOLDER OUT.npz``
(about 1 minute per 100 photos at 1280x960).

Example (about 1 minute per 100 photos at 1280x960)::

    python -m monodbh.toolkit.evaluation.fit_rope_stem --fit data/calset data/calset2 --test data/bench \\
        --negatives /work/shared/data/real_trees

Imported by the rope verifier's tests (a command otherwise); imports the pipeline's session and
working image, ``toolkit.rope``, ``toolkit.rope.stem_search``, ``models.runtime.rope_verifier``, the training's
data sources and :mod:`.synth_samples`.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import sys

import numpy as np

__all__ = ["collect", "collect_patches", "fit_logistic", "photo_report", "main"]

FEATURES = ("log_contrast", "log_zpix", "log_zprof", "log_width", "second", "red_shift", "h_lo", "h_hi",
            "main", "orange")


def _rope_pixel(meta: dict, K_pinhole: np.ndarray | None = None) -> np.ndarray | None:
    """(2,) photo pixel of the rope ring's centre, or None without a rope; with ``K_pinhole``
    the pixel in that undistorted pinhole image."""
    import cv2

    if not meta.get("rope"):
        return None
    R, t = np.array(meta["R_world_from_cam"]), np.array(meta["t_world_from_cam"])
    pc = R.T @ (np.array(meta["rope"]["center_world"]) - t)
    if K_pinhole is not None:
        q = np.asarray(K_pinhole, float) @ pc
        return q[:2] / q[2]
    uv, _ = cv2.projectPoints(pc[None], np.zeros(3), np.zeros(3), np.array(meta["K"]),
                              np.array(meta.get("dist") or np.zeros(5)))
    return uv.ravel()


def collect(folders, session=None, long_side: int = 1600) -> list[dict]:
    """One row per stem band of every ``*.jpg`` in ``folders``: features, score, label, photo.

    Photos without a ``.json`` beside them are rope-free negatives.
    """
    import cv2

    from monodbh.toolkit.pipeline import Session
    from monodbh.toolkit.rope import detect_rope
    from monodbh.toolkit.rope.stem_search import stem_bands, trunk_like

    sess = session or Session()
    rows = []
    for folder in folders:
        for fn in sorted(glob.glob(os.path.join(folder, "*.jpg"))):
            rgb = cv2.imread(fn, cv2.IMREAD_COLOR)
            if rgb is None:
                continue
            rgb = np.ascontiguousarray(rgb[:, :, ::-1])
            if max(rgb.shape[:2]) > long_side:
                s = long_side / max(rgb.shape[:2])
                rgb = cv2.resize(rgb, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
            inst = sess.segmenter.predict(rgb, size=(rgb.shape[1], rgb.shape[0])).instance
            det = detect_rope(rgb, None, weak_score=-50.0)
            js = fn[:-4] + ".json"
            uv = _rope_pixel(json.load(open(js))) if os.path.exists(js) else None
            for b in stem_bands(rgb, inst, rope_candidates=det.candidates):
                rows.append(dict(photo=fn, roped=uv is not None, found_by_band=bool(det) and not det.weak,
                                 label=_on_rope(b, uv), trunk_like=trunk_like(b), **{k: b.features[k] for k in FEATURES}))
    return rows


def _on_rope(b, uv) -> int:
    """1 when band ``b`` lies on the rope centre ``uv`` (see the module docstring), else 0."""
    return int(uv is not None and abs(b.center_xy[1] - uv[1]) <= max(8, 0.2 * b.width_px)
               and abs(b.center_xy[0] - uv[0]) <= max(8, b.width_px))


def collect_patches(folder: str, out: str, session=None, per_stem: int = 4, long_side: int = 1600,
                    verbose: bool = True) -> dict:
    """The rope verifier's examples (``monodbh.models.training.rope_verifier``) from a ``dbh synth``
    folder, written to ``out`` (``.npz``) and returned.

    Every photo is made the pipeline's working image (:func:`monodbh.toolkit.frames.work_frame`), segmented, and searched for stem bands
    (``per_stem`` per stem); each band gives its patch (:func:`monodbh.models.runtime.rope_verifier.band_patch`),
    side features, the label (on the true rope or not, as :func:`collect`), the stem search's
    score and whether it is :func:`~monodbh.toolkit.rope.stem_search.trunk_like`.

    Arrays: ``patch`` (N, PATCH_H, PATCH_W, 3) uint8, ``stem``/``inside`` (N, PATCH_H, PATCH_W)
    bool, ``side`` (N, N_SIDE) float32, ``label`` (N,) uint8, ``score`` (N,) float32,
    ``trunk_like`` (N,) bool, ``photo`` (N,) int (the sample index), ``roped`` (N,) bool, and
    ``found_by_band`` (N,) bool (the band detector found the rope there without the stem search).
    """
    import time

    from monodbh.models.runtime.rope_verifier import band_patch, side_vector
    from monodbh.models.training.common import make_source
    from monodbh.toolkit.config import MeasureConfig
    from monodbh.toolkit.frames import work_frame
    from monodbh.toolkit.pipeline import Session
    from monodbh.toolkit.rope import detect_rope
    from monodbh.toolkit.rope.stem_search import stem_bands, trunk_like

    from .synth_samples import camera_from_meta

    sess = session or Session()
    src = make_source(folder)
    acc: dict = {k: [] for k in ("patch", "stem", "inside", "side", "label", "score", "trunk_like", "photo",
                                 "roped", "found_by_band")}
    t0 = time.perf_counter()
    for i in range(len(src)):
        try:
            smp = src.get(i)
        except (OSError, ValueError, KeyError) as e:
            print(f"{folder}: sample {i} skipped ({e})", flush=True)
            continue
        meta = smp["meta"]
        # the pipeline's working image (downscaled, undistorted with alpha 0) and its pinhole camera
        cam0 = camera_from_meta(meta)
        frame = work_frame(smp["rgb"], cam0, MeasureConfig().work_long_side_px)
        rgb, cam = frame.image, frame.camera
        inst = sess.segmenter.predict(rgb, size=(rgb.shape[1], rgb.shape[0])).instance
        det = detect_rope(rgb, None, weak_score=MeasureConfig().rope.weak_score)
        uv = _rope_pixel(meta, cam.K)
        by_band = bool(det) and not det.weak and uv is not None and \
            float(np.hypot(det.center_xy[0] - uv[0], det.center_xy[1] - uv[1])) < 20
        for b in stem_bands(rgb, inst, rope_candidates=det.candidates, per_stem=per_stem, unclipped_red=True):
            p, st, ins = band_patch(rgb, inst == b.tree_id, b.center_xy, b.direction, max(b.width_px, 1))
            for k, v in (("patch", p), ("stem", st), ("inside", ins), ("side", side_vector(b.features)),
                         ("label", _on_rope(b, uv)), ("score", b.score), ("trunk_like", trunk_like(b)),
                         ("photo", i), ("roped", uv is not None), ("found_by_band", by_band)):
                acc[k].append(v)
        if verbose and (i + 1) % 50 == 0:
            print(f"{folder}: {i + 1}/{len(src)} photos, {len(acc['label'])} bands "
                  f"({sum(acc['label'])} on the rope), {time.perf_counter() - t0:.0f} s", flush=True)
    arr = {k: np.asarray(v) for k, v in acc.items()}
    arr["side"] = arr["side"].astype(np.float32)
    arr["score"] = arr["score"].astype(np.float32)
    arr["label"] = arr["label"].astype(np.uint8)
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    np.savez(out, **arr)
    return arr


def fit_logistic(rows: list[dict], lam: float = 1.0, keys=FEATURES) -> dict:
    """L2-damped logistic regression of ``label`` on ``keys`` (bias undamped) -> weights dict."""
    A = np.array([[1.0] + [r[k] for k in keys] for r in rows])
    y = np.array([r["label"] for r in rows], float)
    w = np.zeros(A.shape[1])
    reg = lam * np.diag(np.r_[0.0, np.ones(len(keys))])
    for _ in range(50):
        p = 1 / (1 + np.exp(-A @ w))
        g = A.T @ (p - y) + reg @ w
        Hm = A.T @ (A * (p * (1 - p))[:, None]) + reg
        w -= np.linalg.solve(Hm, g)
    return {"bias": float(w[0]), **{k: float(v) for k, v in zip(keys, w[1:])}}


def photo_report(rows: list[dict], weights: dict, thr: float) -> dict:
    """Photo-level outcome of the stem search at threshold ``thr`` (trunk-like bands only)."""
    from monodbh.toolkit.rope.stem_search import stem_band_score

    by: dict = {}
    for r in rows:
        by.setdefault(r["photo"], []).append(r)
    out = dict(missed_by_band=0, found=0, wrong=0, rope_free=0, false=0)
    for rs in by.values():
        best = max((r for r in rs if r["trunk_like"]), key=lambda r: stem_band_score(r, weights), default=None)
        ok = best is not None and stem_band_score(best, weights) > thr
        if rs[0]["roped"]:
            if rs[0]["found_by_band"]:
                continue
            out["missed_by_band"] += 1
            out["found" if ok and best["label"] else "wrong"] += int(ok)
        else:
            out["rope_free"] += 1
            out["false"] += int(ok)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m monodbh.toolkit.evaluation.fit_rope_stem", description=__doc__.split("\n")[0])
    ap.add_argument("--bank", nargs=2, metavar=("FOLDER", "OUT_NPZ"),
                    help="instead: cut the rope verifier's examples of one dbh synth folder (collect_patches)")
    ap.add_argument("--fit", nargs="+", help="dbh synth folders to fit the weights on")
    ap.add_argument("--test", nargs="*", default=[], help="dbh synth folders to report on only")
    ap.add_argument("--negatives", nargs="*", default=[], help="folders of rope-free photos")
    ap.add_argument("--thresholds", type=float, nargs="+", default=[-2.0, -1.0, 0.0, 1.0])
    a = ap.parse_args(argv)
    if a.bank:
        arr = collect_patches(a.bank[0], a.bank[1])
        print(f"{a.bank[1]}: {len(arr['label'])} bands, {int(arr['label'].sum())} on the rope")
        return 0
    if not a.fit:
        ap.error("--fit or --bank is needed")
    from monodbh.toolkit.pipeline import Session
    from monodbh.toolkit.rope.config import StemSearchConfig
    STEM_WEIGHTS = StemSearchConfig().weights
    sess = Session()
    fit_rows = collect(a.fit, sess)
    w = fit_logistic(fit_rows)
    print(f"fitted on {len(fit_rows)} bands ({sum(r['label'] for r in fit_rows)} on the rope):")
    print("STEM_WEIGHTS = " + json.dumps({k: round(v, 3) for k, v in w.items()}))
    print("shipped       " + json.dumps(STEM_WEIGHTS))
    sets = [("fit: " + " ".join(a.fit), fit_rows)] + [(f, collect([f], sess)) for f in a.test + a.negatives]
    for name, rows in sets:
        for thr in a.thresholds:
            print(f"{name}  threshold {thr:+.1f}  fitted {photo_report(rows, w, thr)}  shipped "
                  f"{photo_report(rows, STEM_WEIGHTS, thr)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
