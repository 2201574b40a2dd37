"""``dbh summary``: the stand summary of results CSVs (trees, mean / quadratic mean DBH, basal area).

Top-level imports stay light (typer only); numpy, the summary library
(:mod:`monodbh.toolkit.outputs.stand`) and rich are imported inside the command.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import List, Optional

import typer

from .measure_cmd import fail

__all__ = ["summary"]


def _check_area(value: Optional[float]) -> Optional[float]:
    if value is not None and not (math.isfinite(value) and value > 0):
        raise typer.BadParameter(f"the plot area must be a finite number of m^2 > 0, got {value:g}")
    return value


def summary(
    results: List[Path] = typer.Argument(..., metavar="RESULTS.csv",
                                         help="Results CSVs of dbh measure --csv: one plot per file, "
                                              "or per value of a 'plot' column.", show_default=False),
    plot_area_m2: Optional[float] = typer.Option(None, "--plot-area-m2", min=0.0, callback=_check_area,
                                                 help="Horizontal area of each plot in m^2 (> 0): adds "
                                                      "stems and basal area per hectare.",
                                                 show_default=False),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Also write the figures to this JSON "
                                            "file (written atomically).", show_default=False),
) -> None:
    """Summarise measured trees per plot and for all plots: photos, trees, mean and quadratic
    mean DBH (cm, with the standard error of the mean), min/max, basal area (m^2, 1-sigma from
    each tree's dbh_sigma_cm), per hectare with --plot-area-m2, and 5 cm DBH classes.

    Exit status: 0 done, 1 bad input (a missing file, no dbh_cm column, a bad number: one
    line naming the file and the row), 2 on usage errors.
    """
    from monodbh.calib import MonodbhError
    from monodbh.toolkit.outputs.stand import stand_summary

    from .measure_cmd import check_outputs

    check_outputs(results, [("--json", json_out)])
    try:
        stand = stand_summary(results, plot_area_m2)
        if json_out is not None:
            _write_json(json_out, stand)
    except MonodbhError as exc:
        raise fail(str(exc))
    from rich.console import Console

    console = Console()
    _plots_table(stand, console)
    _classes_table(stand, console)


def _write_json(path: Path, stand) -> None:
    import json

    from monodbh.calib import MonodbhError
    from monodbh.toolkit.outputs.atomic import atomic_write_text
    from monodbh.toolkit.outputs.paths import check_file_target, printable

    p = check_file_target(path, "--json")
    try:
        atomic_write_text(p, json.dumps(stand.to_json_dict(), indent=1, ensure_ascii=False,
                                        allow_nan=False) + "\n")
    except OSError as exc:
        raise MonodbhError(f"--json {printable(p)}: cannot write ({exc.strerror or exc})") from None


def _num(v: Optional[float], fmt: str = ".1f", sigma: Optional[float] = None) -> str:
    """``"20.0±5.8"`` (compact: the plot table fits 80 columns); ``"-"`` without a value."""
    if v is None:
        return "-"
    return f"{v:{fmt}}" + (f"±{sigma:{fmt}}" if sigma is not None else "")


def _new_table(title: str):
    from rich import box
    from rich.table import Table

    return Table(title=title, show_header=True, header_style="bold", expand=False, box=box.SIMPLE_HEAD,
                 padding=(0, 0), pad_edge=False, title_justify="left")


def _plots_table(stand, console) -> None:
    from monodbh.toolkit.outputs.paths import printable

    per_ha = stand.plot_area_m2 is not None
    t = _new_table("Plots" + (f" ({stand.plot_area_m2:g} m² each)" if per_ha else ""))
    t.add_column("plot", overflow="fold", min_width=8)
    heads = ["photos", "trees", "mean DBH\ncm ±SE", "QMD\ncm", "min-max\ncm", "basal area\nm² ±1σ"]
    if per_ha:
        heads += ["stems\n/ha", "BA m²/ha\n±1σ"]
    for name in heads:
        t.add_column(name, justify="right", no_wrap=True)
    rows = list(stand.plots)
    for k, p in enumerate([*rows, stand.all_plots]):
        span = "-" if p.dbh_min_cm is None else f"{p.dbh_min_cm:.1f}-{p.dbh_max_cm:.1f}"
        cells = [printable(p.plot), str(p.photos), str(p.trees),
                 _num(p.dbh_mean_cm, ".1f", p.dbh_mean_se_cm), _num(p.dbh_quadratic_mean_cm),
                 span, _num(p.basal_area_m2, ".3f", p.basal_area_sigma_m2 if p.trees else None)]
        if per_ha:
            cells += [_num(p.stems_per_ha, ".0f"),
                      _num(p.basal_area_m2_per_ha, ".2f", p.basal_area_sigma_m2_per_ha if p.trees else None)]
        t.add_row(*cells, style="bold" if k == len(rows) else None, end_section=k == len(rows) - 1)
    console.print(t)
    notes = ["QMD: quadratic mean DBH; BA: basal area; 1σ from the trees' dbh_sigma_cm"]
    missing = stand.all_plots.trees_without_sigma
    if missing:
        notes.append(f"{missing} tree{'s' if missing != 1 else ''} without dbh_sigma_cm left out of the 1σ")
    if stand.all_plots.not_measured:
        notes.append(f"{stand.all_plots.not_measured} of {stand.all_plots.photos} photos not measured")
    console.print("; ".join(notes), style="dim", highlight=False)


def _classes_table(stand, console) -> None:
    if not stand.dbh_classes:
        console.print("no measured trees: no DBH classes", style="dim", highlight=False)
        return
    per_ha = stand.plot_area_m2 is not None
    t = _new_table("DBH classes (all plots" + (f", {stand.all_plots.area_m2:g} m²)" if per_ha else ")"))
    t.add_column("DBH cm", no_wrap=True)
    t.add_column("trees", justify="right", no_wrap=True)
    t.add_column("basal area m²", justify="right", no_wrap=True)
    if per_ha:
        t.add_column("stems/ha", justify="right", no_wrap=True)
        t.add_column("BA m²/ha", justify="right", no_wrap=True)
    for c in stand.dbh_classes:
        cells = [c.dbh_class_cm, str(c.trees), f"{c.basal_area_m2:.4f}"]
        if per_ha:
            cells += [f"{c.stems_per_ha:.0f}", f"{c.basal_area_m2_per_ha:.2f}"]
        t.add_row(*cells)
    console.print(t)
