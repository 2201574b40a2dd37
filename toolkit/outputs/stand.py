"""The stand summary of measured trees: counts, mean and quadratic mean DBH, basal area, 5 cm classes.

Reads the results CSVs that ``dbh measure --csv`` writes (columns of
:data:`~monodbh.toolkit.result.RESULT_FIELDS`; only ``dbh_cm`` is required, ``dbh_sigma_cm``,
``error``, ``photo`` and ``plot`` are read when present) and sums them up the way a forester
reports a stand. Imported by ``dbh summary``; imports numpy, :mod:`csv` and ``monodbh.calib.errors``.

Plots
    One CSV is one plot (named by its path), unless the CSV has a ``plot`` column: then each
    distinct value is a plot (rows of the same value in several files make one plot). A CSV with
    a header and no rows is a plot with 0 trees.
Measured trees
    A row whose ``error`` is set or whose ``dbh_cm`` is empty is a photo not measured; it counts
    in ``photos`` only.
Figures (per plot and for all plots together), with d_i the DBH of tree i in cm, n trees
    - mean DBH: ``sum(d_i) / n``; its standard error ``s / sqrt(n)`` with ``s`` the sample
      standard deviation (``ddof=1``; none when n < 2);
    - quadratic mean DBH: ``sqrt(sum(d_i^2) / n)`` (the DBH of the tree of mean basal area);
    - basal area ``BA = sum(pi * (d_i / 200)^2)`` m^2 (d_i / 200 is the radius in metres);
    - its 1-sigma from each tree's ``dbh_sigma_cm`` sigma_i, trees independent (first-order
      propagation, ``dBA_i/dd_i = pi * d_i / 20000`` m^2 per cm):
      ``sigma_BA = sqrt(sum((pi * d_i * sigma_i / 20000)^2))`` m^2; trees without a sigma add
      nothing and are counted in ``trees_without_sigma``;
    - with the plot area A (m^2): ``stems_per_ha = n * 10000 / A`` and
      ``basal_area_m2_per_ha = BA * 10000 / A`` (its sigma scaled alike). For all plots
      together the area is ``A * plots`` (every plot has the same area), which is the mean of
      the plots' per-hectare figures.
DBH classes
    5 cm wide, ``[0, 5), [5, 10), ...`` labelled ``"0-5"``, ``"5-10"``; every class from the
    smallest to the largest occupied one is listed, empty ones with 0 trees.

Bad input (a missing or unreadable file, no ``dbh_cm`` column, a ``dbh_cm`` or ``dbh_sigma_cm``
that is not a finite number >= 0) raises :class:`ResultsFileError`, one line naming the file
and the row (rows numbered as in a spreadsheet: the header is row 1).
"""
from __future__ import annotations

import csv
import math
import os
from dataclasses import asdict, dataclass, field
from typing import Iterable, Optional, Sequence

import numpy as np

from monodbh.calib.errors import MonodbhError

__all__ = ["ResultsFileError", "PlotTrees", "PlotSummary", "DbhClass", "StandSummary",
           "CLASS_WIDTH_CM", "read_plots", "basal_area_m2", "basal_area_sigma_m2",
           "summarise_plot", "summarise_all", "dbh_classes", "stand_summary"]

#: width of the DBH classes, cm
CLASS_WIDTH_CM = 5.0

#: m^2 in a hectare
_M2_PER_HA = 10000.0


class ResultsFileError(MonodbhError):
    """A results CSV cannot be summarised: missing, unreadable, no ``dbh_cm`` column, a bad number."""


@dataclass
class PlotTrees:
    """The measured trees of one plot.

    Attributes
    ----------
    plot : str
        The plot's name: the ``plot`` column's value, else the CSV's path.
    photos : int
        Rows (photos) of the plot, measured or not.
    dbh_cm : (n,) float64 ndarray
        DBH of each measured tree, cm.
    dbh_sigma_cm : (n,) float64 ndarray
        1-sigma of each DBH, cm; NaN where the row has none.
    sources : list of str
        The CSVs the plot's rows came from.
    """
    plot: str
    photos: int = 0
    dbh_cm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    dbh_sigma_cm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    sources: list = field(default_factory=list)

    @property
    def trees(self) -> int:
        """Measured trees, n."""
        return int(len(self.dbh_cm))


@dataclass
class PlotSummary:
    """The figures of one plot (or of all plots together: ``plot == "all plots"``).

    DBH figures are None without trees; the standard error is None with fewer than 2 trees;
    per-hectare figures are None without a plot area.
    """
    plot: str
    plots: int
    photos: int
    trees: int
    not_measured: int
    dbh_mean_cm: Optional[float]
    dbh_mean_se_cm: Optional[float]
    dbh_quadratic_mean_cm: Optional[float]
    dbh_min_cm: Optional[float]
    dbh_max_cm: Optional[float]
    basal_area_m2: float
    basal_area_sigma_m2: float
    trees_without_sigma: int
    area_m2: Optional[float] = None
    stems_per_ha: Optional[float] = None
    basal_area_m2_per_ha: Optional[float] = None
    basal_area_sigma_m2_per_ha: Optional[float] = None


@dataclass
class DbhClass:
    """One DBH class ``[lower_cm, upper_cm)`` of all plots together."""
    dbh_class_cm: str
    lower_cm: float
    upper_cm: float
    trees: int
    basal_area_m2: float
    stems_per_ha: Optional[float] = None
    basal_area_m2_per_ha: Optional[float] = None


@dataclass
class StandSummary:
    """Per-plot summaries, the all-plots summary and the DBH classes (see the module docstring)."""
    files: list
    plot_area_m2: Optional[float]
    plots: list
    all_plots: PlotSummary
    dbh_classes: list

    def to_json_dict(self) -> dict:
        """JSON-serialisable dict (plain floats, None for missing figures)."""
        return {"files": list(self.files), "plot_area_m2": self.plot_area_m2,
                "plots": [asdict(p) for p in self.plots], "all_plots": asdict(self.all_plots),
                "dbh_classes": [asdict(c) for c in self.dbh_classes]}


# ---------------------------------------------------------------------------------- reading
def _printable(text: object) -> str:
    from .paths import printable

    return printable(text)


def _number(raw: str, column: str, where: str) -> float:
    """A cell as a finite number >= 0, else :class:`ResultsFileError` naming ``where``."""
    try:
        v = float(raw)
    except ValueError:
        raise ResultsFileError(f"{where}: {column} {_printable(raw)!r} is not a number") from None
    if not math.isfinite(v):
        raise ResultsFileError(f"{where}: {column} {_printable(raw)!r} is not finite")
    if v < 0:
        raise ResultsFileError(f"{where}: {column} {_printable(raw)!r} is negative")
    return v


def _open_rows(path: str) -> tuple[list[str], list[tuple[int, dict]]]:
    """The header and the ``(row number, cells)`` of a CSV; rows numbered with the header as 1."""
    label = _printable(path)
    if os.path.isdir(path):
        raise ResultsFileError(f"{label}: is a folder, not a results CSV")
    try:
        with open(path, encoding="utf-8-sig", newline="") as f:
            reader = csv.reader(f)
            try:
                header = [h.strip() for h in next(reader)]
            except StopIteration:
                header = []
            rows = []
            for cells in reader:
                if not any(c.strip() for c in cells):
                    continue                          # blank line
                rows.append((reader.line_num, dict(zip(header, cells))))
    except FileNotFoundError:
        raise ResultsFileError(f"{label}: no such file") from None
    except UnicodeDecodeError:
        raise ResultsFileError(f"{label}: not a UTF-8 text CSV") from None
    except csv.Error as exc:
        raise ResultsFileError(f"{label}: not a CSV ({exc})") from None
    except OSError as exc:
        raise ResultsFileError(f"{label}: cannot read ({exc.strerror or exc})") from None
    if "dbh_cm" not in header:
        raise ResultsFileError(f"{label}: no dbh_cm column: not a results CSV of dbh measure")
    return header, rows


def _read_one(path: str, plots: dict) -> None:
    """Add the rows of one CSV to ``plots`` (plot name -> lists of photos, DBHs, sigmas, sources)."""
    header, rows = _open_rows(path)
    label = _printable(path)
    by_column = "plot" in header
    if not rows:
        _plot(plots, label, label)
    for line, cells in rows:
        photo = (cells.get("photo") or "").strip()
        where = f"{label}: row {line}" + (f" ({_printable(photo)})" if photo else "")
        name = label
        if by_column:
            name = (cells.get("plot") or "").strip()
            if not name:
                raise ResultsFileError(f"{where}: empty plot")
        entry = _plot(plots, name, label)
        entry["photos"] += 1
        raw = (cells.get("dbh_cm") or "").strip()
        dbh = _number(raw, "dbh_cm", where) if raw else None
        raw_sigma = (cells.get("dbh_sigma_cm") or "").strip()
        sigma = _number(raw_sigma, "dbh_sigma_cm", where) if raw_sigma else math.nan
        if dbh is None or (cells.get("error") or "").strip():
            continue
        entry["dbh"].append(dbh)
        entry["sigma"].append(sigma)


def _plot(plots: dict, name: str, source: str) -> dict:
    entry = plots.setdefault(name, {"photos": 0, "dbh": [], "sigma": [], "sources": []})
    if source not in entry["sources"]:
        entry["sources"].append(source)
    return entry


def read_plots(paths: Iterable[str | os.PathLike]) -> list[PlotTrees]:
    """The plots of one or several results CSVs, in the order they first appear.

    Parameters
    ----------
    paths : iterable of path
        Results CSVs of ``dbh measure --csv``; the same file twice is refused.

    Returns
    -------
    list of PlotTrees

    Raises
    ------
    ResultsFileError
        A file is missing or unreadable, has no ``dbh_cm`` column, a row's ``dbh_cm`` or
        ``dbh_sigma_cm`` is not a finite number >= 0, or a ``plot`` cell is empty.
    """
    plots: dict = {}
    seen: list[str] = []
    for p in paths:
        p = os.fspath(p)
        for q in seen:
            if q == p or (os.path.exists(p) and os.path.exists(q) and os.path.samefile(p, q)):
                raise ResultsFileError(f"{_printable(p)}: given twice (as {_printable(q)})")
        seen.append(p)
        _read_one(p, plots)
    return [PlotTrees(plot=name, photos=e["photos"], dbh_cm=np.asarray(e["dbh"], np.float64),
                      dbh_sigma_cm=np.asarray(e["sigma"], np.float64), sources=e["sources"])
            for name, e in plots.items()]


# ---------------------------------------------------------------------------------- figures
def basal_area_m2(dbh_cm: np.ndarray) -> np.ndarray:
    """Basal area of each tree, ``pi * (d / 200)^2``.

    Parameters
    ----------
    dbh_cm : (n,) array_like
        DBH, cm.

    Returns
    -------
    (n,) float64 ndarray
        Cross-section area at breast height, m^2.
    """
    d = np.asarray(dbh_cm, np.float64)
    return math.pi * (d / 200.0) ** 2


def basal_area_sigma_m2(dbh_cm: np.ndarray, dbh_sigma_cm: np.ndarray) -> float:
    """1-sigma of the basal area sum of independent trees, first-order propagation.

    ``sigma_BA_i = pi * d_i * sigma_i / 20000`` (the derivative of ``pi * (d / 200)^2`` with d in
    cm), summed in quadrature: ``sqrt(sum(sigma_BA_i^2))``. Trees whose sigma is NaN add nothing.

    Parameters
    ----------
    dbh_cm : (n,) array_like
        DBH, cm.
    dbh_sigma_cm : (n,) array_like
        1-sigma of each DBH, cm (NaN: unknown).

    Returns
    -------
    float
        m^2.
    """
    d = np.asarray(dbh_cm, np.float64)
    s = np.asarray(dbh_sigma_cm, np.float64)
    per_tree = math.pi * d * s / 20000.0
    return float(math.sqrt(np.sum(per_tree[np.isfinite(per_tree)] ** 2)))


def _per_ha(value: float, area_m2: Optional[float]) -> Optional[float]:
    return None if area_m2 is None else float(value * _M2_PER_HA / area_m2)


def _summary(name: str, plots: int, photos: int, d: np.ndarray, s: np.ndarray,
             area_m2: Optional[float]) -> PlotSummary:
    n = len(d)
    ba = float(np.sum(basal_area_m2(d)))
    ba_sigma = basal_area_sigma_m2(d, s)
    return PlotSummary(
        plot=name, plots=plots, photos=photos, trees=n, not_measured=photos - n,
        dbh_mean_cm=float(np.mean(d)) if n else None,
        dbh_mean_se_cm=float(np.std(d, ddof=1) / math.sqrt(n)) if n >= 2 else None,
        dbh_quadratic_mean_cm=float(math.sqrt(np.mean(d ** 2))) if n else None,
        dbh_min_cm=float(np.min(d)) if n else None, dbh_max_cm=float(np.max(d)) if n else None,
        basal_area_m2=ba, basal_area_sigma_m2=ba_sigma,
        trees_without_sigma=int(np.sum(~np.isfinite(s))),
        area_m2=area_m2, stems_per_ha=_per_ha(n, area_m2), basal_area_m2_per_ha=_per_ha(ba, area_m2),
        basal_area_sigma_m2_per_ha=_per_ha(ba_sigma, area_m2))


def summarise_plot(plot: PlotTrees, plot_area_m2: Optional[float] = None) -> PlotSummary:
    """The figures of one plot (formulas in the module docstring).

    Parameters
    ----------
    plot : PlotTrees
    plot_area_m2 : float, optional
        The plot's horizontal area, m^2 (> 0); gives the per-hectare figures.
    """
    return _summary(plot.plot, 1, plot.photos, plot.dbh_cm, plot.dbh_sigma_cm, plot_area_m2)


def summarise_all(plots: Sequence[PlotTrees], plot_area_m2: Optional[float] = None) -> PlotSummary:
    """The figures of all plots together: the trees pooled, the area ``plot_area_m2 * len(plots)``.

    The standard error of the mean DBH is that of the pooled trees (plots not weighted).
    """
    d = np.concatenate([p.dbh_cm for p in plots]) if plots else np.zeros(0)
    s = np.concatenate([p.dbh_sigma_cm for p in plots]) if plots else np.zeros(0)
    area = None if plot_area_m2 is None else plot_area_m2 * len(plots)
    return _summary("all plots", len(plots), sum(p.photos for p in plots), d, s, area)


def dbh_classes(dbh_cm: np.ndarray, area_m2: Optional[float] = None,
                width_cm: float = CLASS_WIDTH_CM) -> list[DbhClass]:
    """Trees and basal area by DBH class ``[k * width, (k + 1) * width)``.

    Parameters
    ----------
    dbh_cm : (n,) array_like
        DBH, cm (>= 0).
    area_m2 : float, optional
        The area the trees stand on, m^2; gives the per-hectare figures.
    width_cm : float
        Class width, cm.

    Returns
    -------
    list of DbhClass
        From the smallest to the largest occupied class, empty classes between them included;
        empty without trees.
    """
    d = np.asarray(dbh_cm, np.float64)
    if not len(d):
        return []
    k = np.floor(d / width_cm).astype(np.int64)
    ba = basal_area_m2(d)
    out = []
    for c in range(int(k.min()), int(k.max()) + 1):
        sel = k == c
        lo, hi = c * width_cm, (c + 1) * width_cm
        n, ba_c = int(np.sum(sel)), float(np.sum(ba[sel]))
        out.append(DbhClass(dbh_class_cm=f"{lo:g}-{hi:g}", lower_cm=float(lo), upper_cm=float(hi),
                            trees=n, basal_area_m2=ba_c, stems_per_ha=_per_ha(n, area_m2),
                            basal_area_m2_per_ha=_per_ha(ba_c, area_m2)))
    return out


def stand_summary(paths: Iterable[str | os.PathLike],
                  plot_area_m2: Optional[float] = None) -> StandSummary:
    """Read results CSVs and summarise them: per plot, all plots together, DBH classes.

    Parameters
    ----------
    paths : iterable of path
        Results CSVs (:func:`read_plots`).
    plot_area_m2 : float, optional
        The area of each plot, m^2 (finite, > 0).

    Raises
    ------
    ResultsFileError
        Bad input (:func:`read_plots`).
    ValueError
        ``plot_area_m2`` not finite and > 0 (a programming error; the CLI checks it).
    """
    if plot_area_m2 is not None and not (math.isfinite(plot_area_m2) and plot_area_m2 > 0):
        raise ValueError(f"plot_area_m2 must be finite and > 0, got {plot_area_m2!r}")
    paths = [os.fspath(p) for p in paths]
    plots = read_plots(paths)
    every = summarise_all(plots, plot_area_m2)
    d = np.concatenate([p.dbh_cm for p in plots]) if plots else np.zeros(0)
    return StandSummary(files=[_printable(p) for p in paths], plot_area_m2=plot_area_m2,
                        plots=[summarise_plot(p, plot_area_m2) for p in plots], all_plots=every,
                        dbh_classes=dbh_classes(d, every.area_m2))
