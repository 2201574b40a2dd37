"""``dbh eval``: measure every sample of a ``dbh synth`` folder and score the DBH against the truth.

:func:`read_eval_samples` reads the samples' records, :func:`eval_jobs` makes their
``toolkit.batch`` jobs (with the simulated taps and rope diameters of the chosen mode),
:func:`eval_record` joins a result to its sample's truth, :func:`eval_metrics` and
:func:`stage_stats` score the records, :func:`eval_report` is the ``--json`` report and
:func:`print_eval` prints the tables.

Imported by ``monodbh.cli.eval_cmd``; imports ``toolkit.batch`` and the evaluation modules
:mod:`.synth_samples` and :mod:`.taps` (rich only to print).
"""
from __future__ import annotations

import json
import math
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from monodbh.calib.errors import MonodbhError
from monodbh.toolkit.batch import Job

from .synth_samples import camera_from_meta, gt_dbh_cm, gt_rope_px, gt_silhouette, on_true_rope, true_rope_diameter_m
from .taps import sample_base_tap, sample_rope_tap, true_base_pixel

__all__ = ["EvalSample", "SampleRecordError", "read_eval_samples", "eval_jobs", "eval_record", "eval_report",
           "eval_metrics", "stage_stats", "print_eval", "print_side_by_side", "ROPE_PX_BINS"]


class SampleRecordError(MonodbhError):
    """A sample's ``.json`` record cannot be read or lacks what the evaluation needs."""


@dataclass(frozen=True)
class EvalSample:
    """One sample of the evaluated folder and its true values.

    Attributes
    ----------
    index : int
        The sample's number ``NNNNNN``.
    stem : Path
        ``folder/NNNNNN`` (the photo is ``stem.jpg``).
    meta : dict
        Its record.
    camera : monodbh.calib.Camera
        Its camera (:func:`.synth_samples.camera_from_meta`).
    gt_dbh_cm : float or None
        The roped tree's true DBH; None for a scene without rope.
    gt_rope_px : float or None
        The rope's thickness in photo pixels (:func:`.synth_samples.gt_rope_px`); None
        without rope.
    gt_base_status : str or None
        Where the roped stem meets the ground in the photo (:func:`.taps.true_base_pixel`):
        ``"visible"``, ``"in_clutter"`` (hidden by grass or litter under :data:`BASE_CLUTTER_M`),
        ``"occluded"``, ``"outside"``; None without rope or ground truth.
    gt_distance_m : float or None
        The roped stem's true horizontal distance at 1.3 m (the record's ``distance_m``).
    """
    index: int
    stem: Path
    meta: dict
    camera: Any
    gt_dbh_cm: Optional[float]
    gt_rope_px: Optional[float]
    gt_base_status: Optional[str] = None
    gt_distance_m: Optional[float] = None


def read_eval_samples(folder: Path, indices: Sequence[int]) -> list[EvalSample]:
    """The samples ``indices`` of ``folder`` with their cameras and true values.

    Raises
    ------
    SampleRecordError
        A record cannot be read or parsed (the message names its file).
    """
    out = []
    for i in indices:
        stem = Path(folder) / f"{i:06d}"
        try:
            meta = json.loads(stem.with_suffix(".json").read_text())
            cam = camera_from_meta(meta)
            gt = gt_dbh_cm(meta)
        except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:
            raise SampleRecordError(f"{stem.with_suffix('.json')}: bad sample record "
                                    f"({type(exc).__name__}: {exc})") from None
        out.append(EvalSample(i, stem, meta, cam, gt, gt_rope_px(meta) if gt is not None else None,
                              *(_base_truth(stem, meta) if gt is not None else (None, None))))
    return out


def _base_truth(stem: Path, meta: dict) -> tuple[Optional[str], Optional[float]]:
    """(where the roped stem's base is in the photo, its true distance) of a roped sample."""
    tree = next((t for t in meta.get("trees", []) if t.get("id") == meta.get("roped_tree")), {})
    dist = tree.get("distance_m")
    try:
        depth = np.load(stem.with_suffix(".npz"))["depth"]
        return true_base_pixel(meta, depth, clutter_height_m=BASE_CLUTTER_M)[1], dist
    except (OSError, KeyError, ValueError, TypeError, IndexError, StopIteration):
        return None, dist           # no ground truth (or no pose in the record) to tell


def eval_jobs(samples: Sequence[EvalSample], *, tap_base: bool = False, tap_rope: bool = False,
              tap_noise_px: float = 3.0, rope_known: bool = False, rope_mm: Optional[float] = None,
              out_dir: Optional[Path] = None) -> list[Job]:
    """The batch jobs measuring ``samples`` (in order), as a user of the chosen mode would.

    Parameters
    ----------
    samples : sequence of EvalSample
    tap_base : bool
        Give each photo a simulated stem-base tap (``base_xy``) where the base is visible
        (:func:`.taps.sample_base_tap`, noise ``tap_noise_px`` seeded by the sample's index).
    tap_rope : bool
        Give each photo a simulated rope tap (``pick_xy``) where the rope is visible
        (:func:`.taps.sample_rope_tap`).
    tap_noise_px : float
        1-sigma of the simulated taps, pixels per axis.
    rope_known : bool
        Give each photo its rope's true diameter (``rope_diameter_m``); a rope-free photo gets
        the median marker width of the roped ones, as a user whose camera file holds the width
        of the marker they carry (``dbh marker``) measures every photo with it.
    rope_mm : float, optional
        Give every photo (rope-free ones included) this marker width, as a user whose camera
        file holds it (``dbh marker``) would; instead of ``rope_known``.
    out_dir : Path, optional
        Write overlays (and tree PLYs) there.

    Returns
    -------
    list of toolkit.batch.Job
    """
    jobs = []
    equipment_m = _median_marker_m(samples) if rope_known and rope_mm is None else None
    for n, s in enumerate(samples):
        base_xy = sample_base_tap(s.stem, s.meta, tap_noise_px, s.index) if tap_base else None
        pick_xy = sample_rope_tap(s.stem, s.meta, tap_noise_px, s.index) if tap_rope else None
        rope_m = (rope_mm / 1000.0 if rope_mm is not None
                  else (true_rope_diameter_m(s.meta) or equipment_m) if rope_known else None)
        jobs.append(Job(n, str(s.stem.with_suffix(".jpg")), s.camera, pick_xy=pick_xy, base_xy=base_xy,
                        rope_diameter_m=rope_m, out_dir=str(out_dir) if out_dir else None))
    return jobs


def _median_marker_m(samples: Sequence[EvalSample]) -> Optional[float]:
    """The median true marker width (m) of the roped ``samples``, None without any."""
    widths = [w for w in (true_rope_diameter_m(s.meta) for s in samples) if w]
    return float(np.median(widths)) if widths else None


def eval_record(sample: EvalSample, result: dict) -> dict:
    """One row of the report: the sample's truth joined to its result (``MeasureResult.to_json_dict``).

    Keys ``sample``, ``gt_dbh_cm``, ``gt_rope_px``, ``gt_base_status``, ``gt_distance_m``, ``err_cm``
    (measured - true), ``distance_err_pct`` (measured / true distance - 1, %), ``width_err_pct``
    (the stem's width alone, the scale taken from the truth: the measured DBH-to-distance ratio
    against the true silhouette's, :func:`.synth_samples.gt_silhouette`, - 1, %),
    ``roundness_pct`` (the true silhouette diameter / tape DBH - 1, %: what no single view
    sees), ``width_err_pct_by_estimator`` (the same for each DBH estimator), ``on_true_rope``
    (:func:`.synth_samples.on_true_rope`, for measured roped samples), then the result's fields.
    """
    gt, d = sample.gt_dbh_cm, result
    on = (on_true_rope(sample.stem, sample.meta, d.get("rope_xy"))
          if gt is not None and d["dbh_cm"] is not None else None)
    dist_err = (100.0 * (d["distance_m"] / sample.gt_distance_m - 1.0)
                if d.get("distance_m") is not None and sample.gt_distance_m else None)
    sil = gt_silhouette(sample.meta) if gt else None
    def width_err_of(dbh_cm):
        if not sil or dbh_cm is None or not d.get("distance_m"):
            return None
        return 100.0 * ((dbh_cm / d["distance_m"]) / (100.0 * sil[0] / sil[1]) - 1.0)
    width_err = width_err_of(d.get("dbh_cm"))
    by_est = {k: width_err_of(v) for k, v in (d.get("estimates_cm") or {}).items() if v is not None}
    return {"sample": sample.index, "gt_dbh_cm": gt, "gt_rope_px": sample.gt_rope_px,
            "gt_base_status": sample.gt_base_status, "gt_distance_m": sample.gt_distance_m,
            "err_cm": (d["dbh_cm"] - gt if gt is not None and d["dbh_cm"] is not None else None),
            "distance_err_pct": dist_err, "width_err_pct": width_err,
            "width_err_pct_by_estimator": by_est if width_err is not None else None,
            "roundness_pct": 100.0 * (100.0 * sil[0] / gt - 1.0) if sil else None, "on_true_rope": on, **d}


def eval_report(folder: Path, records: Sequence[dict], jobs: Sequence[Job], metrics: dict, stages: dict, *,
                gt_perception: bool, tap_base: bool, tap_rope: bool, tap_noise_px: float, rope_known: bool,
                interrupted: bool, rope_mm: Optional[float] = None) -> dict:
    """The ``dbh eval --json`` report: the mode, ``metrics`` (:func:`eval_metrics`), ``timings_ms``
    (:func:`stage_stats`) and the rows ``samples`` (:func:`eval_record`)."""
    return {"folder": str(folder), "gt_perception": gt_perception, "interrupted": interrupted,
            "tap_base": ({"noise_px": tap_noise_px, "tapped": sum(j.base_xy is not None for j in jobs)}
                         if tap_base else None),
            "tap_rope": ({"noise_px": tap_noise_px, "tapped": sum(j.pick_xy is not None for j in jobs)}
                         if tap_rope else None),
            "rope_known": rope_known, "rope_mm": rope_mm,
            "metrics": metrics, "timings_ms": stages, "samples": list(records)}


#: thickness bins (pixels, lower edges) of the per-rope-thickness detection table
ROPE_PX_BINS = (0.0, 1.0, 2.0, 3.0, 5.0)


def _stats(v: Sequence[float]) -> Optional[dict]:
    if not v:
        return None
    return {"mean": statistics.fmean(v), "median": statistics.median(v), "n": len(v)}


def stage_stats(timings: Sequence[dict]) -> dict:
    """``{stage: {"mean", "median", "n"}}`` (ms) over the ``timings_ms`` dicts, ``total`` last."""
    stages: dict[str, list[float]] = {}
    for t in timings:
        for k, v in (t or {}).items():
            if v is not None and math.isfinite(float(v)):
                stages.setdefault(k, []).append(float(v))
    order = [k for k in stages if k != "total"] + (["total"] if "total" in stages else [])
    return {k: _stats(stages[k]) for k in order}


def _reason(rec: dict) -> str:
    err = rec["error"] or ""
    p = rec.get("photo") or ""
    return err[len(p) + 2:] if p and err.startswith(p + ": ") else err


def eval_metrics(records: Sequence[dict]) -> dict:
    """Accuracy metrics of per-sample records.

    Parameters
    ----------
    records : sequence of dict
        ``gt_dbh_cm`` (None for no-rope scenes), ``dbh_cm``, ``dbh_sigma_cm``, ``error``.

    Returns
    -------
    dict
        ``samples``, ``roped``, ``no_rope``, ``measured``, ``detection_rate`` (measured / roped),
        ``mae_cm``, ``rel_mae_pct``, ``rmse_cm``, ``bias_cm``, ``median_abs_err_cm``,
        ``p90_abs_err_cm``, ``coverage_1sigma``, ``coverage_2sigma`` (fractions of measured roped
        samples with a sigma whose ``|err| <= k sigma``), ``refusal_rate`` (no-rope scenes
        correctly refused), ``false_measurements`` (no-rope scenes given a DBH),
        ``wrong_rope`` (measured roped samples whose rope is another band: a wrong tree measured,
        of ``rope_checked`` with ground truth to tell), ``failure_reasons`` (roped scenes' error
        messages, counted), ``by_scale_source``,
        ``by_rope_px`` (detection rate and MAE per bin of ``gt_rope_px``, where records have it),
        ``width_median_abs_err_pct``, ``width_p90_abs_err_pct``, ``width_bias_pct`` (the stem's
        width alone, ``width_err_pct``, over the measured samples that have it),
        ``roundness_median_abs_pct``, ``roundness_mean_abs_pct`` (median and mean
        ``|roundness_pct|``: the single-view floor against the tape DBH; the mean is the floor of
        ``rel_mae_pct``), ``silhouette_rel_mae_pct`` (the relative MAE against the true
        silhouette diameter instead of the tape: the error a single view could avoid).
    """
    roped = [r for r in records if r.get("gt_dbh_cm") is not None]
    norope = [r for r in records if r.get("gt_dbh_cm") is None]
    meas = [r for r in roped if r.get("error") is None and r.get("dbh_cm") is not None]
    err = [float(r["dbh_cm"]) - float(r["gt_dbh_cm"]) for r in meas]
    ae = [abs(e) for e in err]
    rel = [abs(e) / float(r["gt_dbh_cm"]) * 100.0 for e, r in zip(err, meas) if r["gt_dbh_cm"] > 0]
    with_sigma = [(abs(e), float(r["dbh_sigma_cm"])) for e, r in zip(err, meas)
                  if r.get("dbh_sigma_cm") is not None and float(r["dbh_sigma_cm"]) > 0]
    refused = [r for r in norope if r.get("error") is not None or r.get("dbh_cm") is None]
    checked = [r for r in meas if r.get("on_true_rope") is not None]
    reasons: dict[str, int] = {}
    for r in roped:
        if r.get("error") is not None:
            reasons[_reason(r)] = reasons.get(_reason(r), 0) + 1

    def mean(v):
        return statistics.fmean(v) if v else None
    by_view = _by_base_view(roped)
    werr = [float(r["width_err_pct"]) for r in meas if r.get("width_err_pct") is not None]
    wabs = sorted(abs(w) for w in werr)
    rnd = [abs(float(r["roundness_pct"])) for r in meas if r.get("roundness_pct") is not None]
    # the DBH against the silhouette diameter (the tape DBH times 1 + roundness)
    sil_rel = [abs((1.0 + e / float(r["gt_dbh_cm"])) / (1.0 + float(r["roundness_pct"]) / 100.0) - 1.0) * 100.0
               for e, r in zip(err, meas) if r.get("roundness_pct") is not None and r["gt_dbh_cm"] > 0]

    return {
        "samples": len(records), "roped": len(roped), "no_rope": len(norope), "measured": len(meas),
        "detection_rate": len(meas) / len(roped) if roped else None,
        "mae_cm": mean(ae), "rel_mae_pct": mean(rel),
        "rmse_cm": math.sqrt(mean([e * e for e in err])) if err else None,
        "bias_cm": mean(err),
        "median_abs_err_cm": statistics.median(ae) if ae else None,
        "p90_abs_err_cm": (sorted(ae)[min(len(ae) - 1, math.ceil(0.9 * len(ae)) - 1)] if ae else None),
        "coverage_1sigma": mean([float(a <= s) for a, s in with_sigma]),
        "coverage_2sigma": mean([float(a <= 2 * s) for a, s in with_sigma]),
        "with_sigma": len(with_sigma),
        "refusal_rate": len(refused) / len(norope) if norope else None,
        "false_measurements": len(norope) - len(refused),
        "wrong_rope": sum(1 for r in checked if not r["on_true_rope"]),
        "rope_checked": len(checked),
        "failure_reasons": dict(sorted(reasons.items(), key=lambda kv: -kv[1])),
        "by_scale_source": _by_source(meas),
        "by_rope_px": _by_rope_px(roped),
        "by_base_view": by_view,
        "wrong_base": sum(v["wrong_base"] for k, v in by_view.items() if k in ("occluded", "outside")),
        "width_median_abs_err_pct": statistics.median(wabs) if wabs else None,
        "width_p90_abs_err_pct": wabs[min(len(wabs) - 1, math.ceil(0.9 * len(wabs)) - 1)] if wabs else None,
        "width_bias_pct": statistics.median(werr) if werr else None,
        "roundness_median_abs_pct": statistics.median(rnd) if rnd else None,
        "roundness_mean_abs_pct": mean(rnd),
        "silhouette_rel_mae_pct": mean(sil_rel),
        "width_by_estimator": _width_by_estimator(meas),
    }


def _width_by_estimator(meas: Sequence[dict]) -> dict:
    """Estimator -> ``{"n", "median_abs_pct", "p90_abs_pct"}`` of its ``width_err_pct``."""
    per: dict[str, list[float]] = {}
    for r in meas:
        for k, v in (r.get("width_err_pct_by_estimator") or {}).items():
            if v is not None:
                per.setdefault(k, []).append(abs(float(v)))
    out = {}
    for k, v in sorted(per.items()):
        v.sort()
        out[k] = {"n": len(v), "median_abs_pct": statistics.median(v),
                  "p90_abs_pct": v[min(len(v) - 1, math.ceil(0.9 * len(v)) - 1)]}
    return out


#: a scale led by a stem base whose distance is off by more than this (%) where the true base is
#: hidden or out of the photo counts as a wrong base (``wrong_base``)
WRONG_BASE_PCT = 15.0
#: a hidden base that a person reads through clutter lower than this (m) is ``"in_clutter"``
#: (grass tufts, leaf litter: the stem-base network's training label, ``docs/decisions/stem-base.md``)
BASE_CLUTTER_M = 0.3


def _base_led(r: dict) -> bool:
    return str(r.get("scale_source") or "").split("+")[0].startswith("stem_base")


def _by_base_view(roped: Sequence[dict]) -> dict:
    """Per true base status (visible / in_clutter / occluded / outside): roped, measured, how many took their
    scale from a stem base, DBH MAE and the median |distance error| (%)."""
    out = {}
    for status in ("visible", "in_clutter", "occluded", "outside"):
        rs = [r for r in roped if r.get("gt_base_status") == status]
        if not rs:
            continue
        ms = [r for r in rs if r.get("error") is None and r.get("dbh_cm") is not None]
        ae = [abs(float(r["dbh_cm"]) - float(r["gt_dbh_cm"])) for r in ms]
        rel = [a / float(r["gt_dbh_cm"]) * 100.0 for a, r in zip(ae, ms)]
        de = [abs(r["distance_err_pct"]) for r in ms if r.get("distance_err_pct") is not None]
        used = [r for r in ms if _base_led(r)]
        out[status] = {"roped": len(rs), "measured": len(ms), "base_used": len(used),
                       "mae_cm": statistics.fmean(ae) if ae else None,
                       "rel_mae_pct": statistics.fmean(rel) if rel else None,
                       "median_abs_distance_err_pct": statistics.median(de) if de else None,
                       "wrong_base": sum(1 for r in used if abs(r.get("distance_err_pct") or 0.0) > WRONG_BASE_PCT)}
    return out


def _by_rope_px(roped: Sequence[dict]) -> dict:
    """Detection rate and MAE of the roped samples per rope thickness bin (``gt_rope_px``).

    Keys ``"lo-hi px"`` (the last ``">=lo px"``); samples without ``gt_rope_px`` are left out.
    """
    out = {}
    edges = list(ROPE_PX_BINS) + [math.inf]
    for lo, hi in zip(edges[:-1], edges[1:]):
        rs = [r for r in roped if r.get("gt_rope_px") is not None and lo <= float(r["gt_rope_px"]) < hi]
        if not rs:
            continue
        ms = [r for r in rs if r.get("error") is None and r.get("dbh_cm") is not None]
        ae = [abs(float(r["dbh_cm"]) - float(r["gt_dbh_cm"])) for r in ms]
        key = f"{lo:g}-{hi:g} px" if math.isfinite(hi) else f">={lo:g} px"
        out[key] = {"roped": len(rs), "measured": len(ms), "detection_rate": len(ms) / len(rs),
                    "mae_cm": statistics.fmean(ae) if ae else None}
    return out


def _by_source(meas: Sequence[dict]) -> dict:
    """DBH accuracy grouped by the leading scale source (the first of ``scale_source``)."""
    groups: dict[str, list] = {}
    for r in meas:
        key = str(r.get("scale_source") or "?").split("+")[0]
        groups.setdefault(key, []).append(r)
    out = {}
    for k, rs in sorted(groups.items(), key=lambda kv: -len(kv[1])):
        ae = [abs(float(r["dbh_cm"]) - float(r["gt_dbh_cm"])) for r in rs]
        rel = [a / float(r["gt_dbh_cm"]) * 100.0 for a, r in zip(ae, rs) if r["gt_dbh_cm"] > 0]
        cov = [float(a <= 2 * float(r["dbh_sigma_cm"])) for a, r in zip(ae, rs) if r.get("dbh_sigma_cm")]
        out[k] = {"n": len(rs), "mae_cm": statistics.fmean(ae), "rel_mae_pct": statistics.fmean(rel) if rel else None,
                  "coverage_2sigma": statistics.fmean(cov) if cov else None}
    return out


# -- tables -----------------------------------------------------------------------------------------
def _fmt(v: Any, fmt: str = "{:.2f}", pct: bool = False) -> str:
    if v is None:
        return "-"
    return f"{v * 100:.1f} %" if pct else fmt.format(v)


def _table(title: str, columns: Sequence[str], rows: Sequence[Sequence[str]], left: Sequence[str] = ()):
    from rich.table import Table

    t = Table(title=title, show_header=True, header_style="bold")
    for c in columns:
        t.add_column(c, justify="left" if c in left else "right")
    for r in rows:
        t.add_row(*r)
    return t


def _accuracy_rows(m: dict) -> list[tuple[str, str]]:
    rows = [
        ("samples (roped / no rope)", f"{m['samples']} ({m['roped']} / {m['no_rope']})"),
        ("detection rate (measured / roped)", f"{_fmt(m['detection_rate'], pct=True)} ({m['measured']})"),
        ("DBH MAE", _fmt(m["mae_cm"], "{:.2f} cm")),
        ("relative MAE", _fmt(m["rel_mae_pct"], "{:.1f} %")),
        ("RMSE", _fmt(m["rmse_cm"], "{:.2f} cm")),
        ("bias (measured - true)", _fmt(m["bias_cm"], "{:+.2f} cm")),
        ("median / p90 |error|", f"{_fmt(m['median_abs_err_cm'], '{:.2f}')} / "
                                 f"{_fmt(m['p90_abs_err_cm'], '{:.2f}')} cm"),
        ("width alone, median / p90 |error|", f"{_fmt(m.get('width_median_abs_err_pct'), '{:.1f}')} / "
                                                   f"{_fmt(m.get('width_p90_abs_err_pct'), '{:.1f}')} %"),
        *[(f"width alone, {k} estimator", f"{_fmt(v['median_abs_pct'], '{:.1f}')} / "
                                           f"{_fmt(v['p90_abs_pct'], '{:.1f}')} % ({v['n']})")
          for k, v in (m.get("width_by_estimator") or {}).items()],
        ("silhouette vs tape (floor), median / mean", f"{_fmt(m.get('roundness_median_abs_pct'), '{:.1f}')} / "
                                                      f"{_fmt(m.get('roundness_mean_abs_pct'), '{:.1f}')} %"),
        ("relative MAE against the silhouette", _fmt(m.get("silhouette_rel_mae_pct"), "{:.1f} %")),
        ("|err| <= 1 sigma", _fmt(m["coverage_1sigma"], pct=True)),
        ("|err| <= 2 sigma", _fmt(m["coverage_2sigma"], pct=True)),
        ("no-rope scenes correctly refused", f"{_fmt(m['refusal_rate'], pct=True)}"
                                            f" ({m['false_measurements']} measured)"),
    ]
    if m.get("rope_checked"):
        rows.insert(2, ("measured on another band (wrong tree)", f"{m['wrong_rope']} of {m['rope_checked']}"))
    return rows


def print_side_by_side(named: dict, console) -> None:
    """One accuracy table with a column per folder (``named``: ``{title: metrics}``, each from
    :func:`eval_metrics`): the benchmark beside the same scenes in the held-out look."""
    from rich.table import Table

    t = Table(title="DBH accuracy, side by side", show_header=True, header_style="bold")
    t.add_column("metric")
    cols = [dict(_accuracy_rows(m)) for m in named.values()]
    for name in named:
        t.add_column(name, justify="right")
    for k in cols[0]:
        t.add_row(k, *[c.get(k, "-") for c in cols])
    console.print(t)


def print_eval(m: dict, stages: dict, console) -> None:
    """Print the tables of ``dbh eval``: accuracy, time per stage, by scale source, by rope
    thickness, failures (``m`` from :func:`eval_metrics`, ``stages`` from :func:`stage_stats`)."""
    from rich.table import Table

    t = Table(title="DBH accuracy", show_header=True, header_style="bold")
    t.add_column("metric")
    t.add_column("value", justify="right")
    for r in _accuracy_rows(m):
        t.add_row(*r)
    console.print(t)
    if stages:
        console.print(_table("time per stage", ("stage", "mean", "median", "n"),
                             [(k, f"{v['mean']:.1f} ms", f"{v['median']:.1f} ms", str(v["n"]))
                              for k, v in stages.items()], left=("stage",)))
    if m.get("by_scale_source"):
        console.print(_table("by leading scale source", ("source", "n", "MAE", "relative MAE", "|err| <= 2 sigma"),
                             [(k, str(v["n"]), _fmt(v["mae_cm"], "{:.2f} cm"), _fmt(v["rel_mae_pct"], "{:.1f} %"),
                               _fmt(v["coverage_2sigma"], pct=True)) for k, v in m["by_scale_source"].items()],
                             left=("source",)))
    if m.get("by_base_view"):
        console.print(_table("by the stem base in the photo (ground truth)",
                             ("base", "roped", "measured", "scale from a base", "base off > 15 %", "MAE",
                              "relative MAE", "median |distance error|"),
                             [(k, str(v["roped"]), str(v["measured"]), str(v["base_used"]), str(v["wrong_base"]),
                               _fmt(v["mae_cm"], "{:.2f} cm"), _fmt(v["rel_mae_pct"], "{:.1f} %"),
                               _fmt(v["median_abs_distance_err_pct"], "{:.1f} %"))
                              for k, v in m["by_base_view"].items()], left=("base",)))
    if m.get("by_rope_px"):
        console.print(_table("by rope thickness (photo px)", ("rope", "roped", "measured", "detection rate", "MAE"),
                             [(k, str(v["roped"]), str(v["measured"]), _fmt(v["detection_rate"], pct=True),
                               _fmt(v["mae_cm"], "{:.2f} cm")) for k, v in m["by_rope_px"].items()],
                             left=("rope",)))
    if m["failure_reasons"]:
        f = Table(title="failures on roped scenes", show_header=True, header_style="bold")
        f.add_column("count", justify="right")
        f.add_column("error", style="red", overflow="fold")
        for k, n in list(m["failure_reasons"].items())[:8]:
            f.add_row(str(n), k)
        console.print(f)
