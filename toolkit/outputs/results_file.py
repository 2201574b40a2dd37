"""The results file of a batch: JSON lines, CSV and summary written as the rows come.

:class:`ResultWriter` writes each :class:`~monodbh.toolkit.result.MeasureResult` as soon as it
is measured: a JSON line on a stream (flushed per line), a CSV row appended and flushed
(``fsync``) per photo, and with an output folder ``results.jsonl`` and ``summary.json``
rewritten atomically (:mod:`.atomic`) at the end, so an interrupted batch loses nothing
already measured; with a GeoJSON path, the trees with a position (:mod:`.geo`) rewritten
atomically whenever a row adds one, and at the end; with a report path, the HTML report
(:mod:`.report`) written atomically at the end (also of an interrupted batch). Imported by ``monodbh.toolkit.batch`` and the CLI.
"""
from __future__ import annotations

import csv
import io
import json
import os
import statistics
from pathlib import Path
from typing import Any, Optional, Sequence

from monodbh.calib.errors import MonodbhError

from ..result import RESULT_FIELDS, MeasureResult
from .atomic import atomic_write_text
from .paths import check_file_target, ensure_folder, fit_name, printable

__all__ = ["ResultWriter", "csv_row", "row_from_csv", "json_default", "summarise", "printable_row"]


def csv_row(d: dict) -> list[str]:
    """CSV cells of a JSON dict: None -> empty, lists/dicts -> compact JSON, numbers as text."""
    cells = []
    for k in RESULT_FIELDS:
        v = d.get(k)
        if v is None:
            cells.append("")
        elif isinstance(v, (list, dict)):
            cells.append(json.dumps(v, separators=(",", ":"), ensure_ascii=False))
        else:
            cells.append(str(v))
    return cells


_JSON_CELLS = ("flags", "timings_ms", "estimates_cm", "rope_xy")
_FLOAT_CELLS = ("dbh_cm", "dbh_sigma_cm", "distance_m", "camera_lat_deg", "camera_lon_deg", "camera_alt_m",
                "gps_accuracy_m", "camera_heading_deg", "stem_bearing_deg", "tree_lat_deg", "tree_lon_deg")


def row_from_csv(cells: Sequence[str]) -> dict:
    """The JSON dict of a CSV row written by :func:`csv_row` (the inverse: empty -> None, JSON
    cells parsed, numbers as numbers).

    Raises
    ------
    ValueError
        A cell that is not what :func:`csv_row` writes.
    """
    d = dict(zip(RESULT_FIELDS, cells))
    out: dict[str, Any] = {}
    for k in RESULT_FIELDS:
        v = d.get(k, "")
        if v == "":
            out[k] = [] if k == "flags" else ({} if k in ("timings_ms", "estimates_cm") else None)
        elif k in _JSON_CELLS:
            out[k] = json.loads(v)
        elif k in _FLOAT_CELLS:
            out[k] = float(v)
        elif k == "tree_id":
            out[k] = int(v)
        else:
            out[k] = v
    return out


def _read_kept_rows(p: Path) -> list[dict]:
    """The rows of results CSV ``p`` (a line cut by a killed run is removed from the file)."""
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise MonodbhError(f"{printable(p)}: cannot read CSV to resume ({exc.strerror or exc})") from None
    if raw and not raw.endswith(b"\n"):
        raw = raw[:raw.rfind(b"\n") + 1]          # the row in flight when the run was killed
        with open(p, "r+b") as f:
            f.truncate(len(raw))
    try:
        rows = list(csv.reader(io.StringIO(raw.decode("utf-8"), newline="")))
    except (UnicodeDecodeError, csv.Error) as exc:
        raise MonodbhError(f"{printable(p)}: not a results CSV to resume ({exc})") from None
    if not rows:
        return []
    if tuple(rows[0]) != RESULT_FIELDS:
        raise MonodbhError(f"{printable(p)}: not a results CSV of this version (its columns differ); "
                           f"give another --csv to resume into, or leave out --resume")
    kept = []
    for n, cells in enumerate(rows[1:], start=2):
        try:
            kept.append(row_from_csv(cells))
        except ValueError:
            raise MonodbhError(f"{printable(p)}: row {n} is not a results row; cannot resume") from None
    return kept


def printable_row(d: dict) -> dict:
    """The row's text fields (photo, error, flags, tag) with non-UTF-8 bytes of file names escaped
    (:func:`~.paths.printable`), so the row can be written as UTF-8 CSV and JSON."""
    out = dict(d)
    for k in ("photo", "error", "scale_source", "tag"):
        if isinstance(out.get(k), str):
            out[k] = printable(out[k])
    if isinstance(out.get("flags"), list):
        out["flags"] = [printable(f) for f in out["flags"]]
    return out


def _json_line(d: dict) -> str:
    return json.dumps(d, ensure_ascii=False, allow_nan=False, default=json_default)


def json_default(o: Any) -> Any:
    """``json.dumps(..., default=json_default)``: numpy scalars and arrays as Python numbers and lists."""
    try:
        import numpy as np

        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:  # pragma: no cover
        pass
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def summarise(results: Sequence[MeasureResult]) -> dict:
    """Counts, DBH range and median stage timings of a batch (JSON-serialisable)."""
    ok = [r for r in results if r.error is None]
    stages: dict[str, list[float]] = {}
    for r in results:
        for k, v in (r.timings_ms or {}).items():
            stages.setdefault(k, []).append(float(v))
    dbh = [float(r.dbh_cm) for r in ok]
    return {
        "photos": len(results), "measured": len(ok), "failed": len(results) - len(ok),
        "failed_photos": [printable(r.photo) for r in results if r.error is not None],
        "dbh_cm": ({"min": round(min(dbh), 2), "median": round(statistics.median(dbh), 2),
                    "max": round(max(dbh), 2)} if dbh else None),
        "timings_ms_median": {k: round(statistics.median(v), 1) for k, v in stages.items()},
    }


class ResultWriter:
    """Write batch rows as they come; finish with atomic ``results.jsonl``/``summary.json``.

    Parameters
    ----------
    json_stream : text stream, optional
        Gets one JSON object per line (exactly :data:`RESULT_FIELDS`), flushed per line.
    csv_path : path, optional
        CSV with a header of :data:`RESULT_FIELDS`; created (truncated) on open, one row
        appended and flushed (``fsync``) per result.
    out_dir : path, optional
        Folder for ``results.jsonl`` and ``summary.json``, rewritten atomically by
        :meth:`finish`.
    meta : dict, optional
        Extra keys for ``summary.json`` (e.g. the calibration file).
    resume : bool
        Keep the rows ``csv_path`` already holds (:attr:`done`: photo -> row) and append to it
        instead of truncating it; a last line cut by a killed run is dropped. The CSV must have
        this version's header. The kept rows count in ``results.jsonl`` and ``summary.json``.
    geojson_path : path, optional
        RFC 7946 FeatureCollection of the rows with a tree position
        (:func:`~.geo.write_geojson`): written (empty) on open, rewritten atomically after each
        row that adds a tree and by :meth:`finish`.
    report_path : path, optional
        The HTML report (:func:`~.report.write_report`) of every row, written atomically by
        :meth:`finish`. Rows carry their thumbnail (``MeasureResult.thumbnail_jpeg``); rows kept
        by ``resume`` get theirs from ``out_dir``'s overlay or their photo.
    report_options : dict, optional
        Keyword arguments of :func:`~.report.render_report` (``meta``, ``plot_area_m2``,
        ``marker_known``, ``title``).

    Use as a context manager; :meth:`add` per result, :meth:`finish` at the end (also on
    interruption, with ``interrupted=True``).
    """

    def __init__(self, *, json_stream: Optional[io.TextIOBase] = None,
                 csv_path: Optional[str | os.PathLike] = None,
                 out_dir: Optional[str | os.PathLike] = None, meta: Optional[dict] = None,
                 resume: bool = False, geojson_path: Optional[str | os.PathLike] = None,
                 report_path: Optional[str | os.PathLike] = None,
                 report_options: Optional[dict] = None) -> None:
        self.json_stream = json_stream
        #: photo (as written in the CSV) -> its row, of the rows kept by ``resume``
        self.done: dict[str, dict] = {}
        self.out_dir = Path(out_dir) if out_dir else None
        self.meta = {k: printable(v) if isinstance(v, str) else v for k, v in (meta or {}).items()}
        self.results: list[MeasureResult] = []
        self._lines: list[str] = []
        self._rows: list[dict] = []
        self._geojson: Optional[Path] = None
        self._report: Optional[Path] = None
        self._report_options = dict(report_options or {})
        self._thumbs: list[Optional[bytes]] = []
        self._n_kept = 0
        self._csv_file = None
        self._csv = None
        if self.out_dir:
            ensure_folder(self.out_dir)
        if csv_path:
            p = check_file_target(csv_path)
            kept = _read_kept_rows(p) if resume and p.exists() else None
            try:
                self._csv_file = open(p, "w" if kept is None else "a", encoding="utf-8", newline="")
            except OSError as exc:
                raise MonodbhError(f"{printable(p)}: cannot write CSV ({exc.strerror or exc})") from None
            self._csv = csv.writer(self._csv_file)
            if kept is None:
                self._csv.writerow(RESULT_FIELDS)
            else:
                for d in kept:
                    self.done[d["photo"]] = d
                    self.results.append(MeasureResult(**d))
                    self._lines.append(_json_line(d))
                    self._rows.append(d)              # their trees stay in --geojson
                    self._thumbs.append(None)         # made by finish() for the report
                self._n_kept = len(kept)
            self._flush_csv()
        if geojson_path:
            self._geojson = check_file_target(geojson_path, "--geojson")
            self._write_geojson()
        if report_path:
            self._report = check_file_target(report_path, "--report")

    def _write_geojson(self) -> None:
        from .geo import write_geojson

        try:
            write_geojson(self._geojson, self._rows)
        except OSError as exc:
            raise MonodbhError(f"{printable(self._geojson)}: cannot write GeoJSON "
                               f"({exc.strerror or exc})") from None

    def _flush_csv(self) -> None:
        self._csv_file.flush()
        try:
            os.fsync(self._csv_file.fileno())
        except OSError:  # pragma: no cover - e.g. pipes
            pass

    def add(self, res: MeasureResult) -> dict:
        """Write one result everywhere; returns its JSON dict."""
        d = printable_row(res.to_json_dict())
        line = _json_line(d)
        self.results.append(res)
        self._lines.append(line)
        if self.json_stream is not None:
            self.json_stream.write(line + "\n")
            self.json_stream.flush()
        if self._csv is not None:
            self._csv.writerow(csv_row(d))
            self._flush_csv()
        self._rows.append(d)
        self._thumbs.append(res.thumbnail_jpeg)
        res.thumbnail_jpeg = None                     # kept once, in _thumbs
        if self._geojson is not None and d.get("tree_lat_deg") is not None and not d.get("error"):
            try:
                self._write_geojson()
            except MonodbhError:  # e.g. disk full: the batch goes on, finish() tries again and says so
                pass
        return d

    def finish(self, *, interrupted: bool = False, extra: Optional[dict] = None) -> Optional[dict]:
        """Close the CSV; write ``results.jsonl`` and ``summary.json`` atomically (out_dir)."""
        if self._csv_file is not None and not self._csv_file.closed:
            self._csv_file.close()
        summary = {**self.meta, **summarise(self.results), "interrupted": interrupted, **(extra or {})}
        if self._geojson is not None:
            self._write_geojson()
        if self._report is not None:
            self._write_report()
        if self.out_dir:
            atomic_write_text(self.out_dir / "results.jsonl", "".join(s + "\n" for s in self._lines))
            atomic_write_text(self.out_dir / "summary.json",
                              json.dumps(summary, indent=1, ensure_ascii=False, default=json_default) + "\n")
        return summary

    def _write_report(self) -> None:
        from .report import thumbnail_from_photo, write_report

        for i, (d, t) in enumerate(zip(self._rows, self._thumbs)):
            if t is None and i < self._n_kept:        # a kept row: its overlay, else its photo
                png = (None if self.out_dir is None
                       else self.out_dir / fit_name(Path(d["photo"]).stem or "photo", "_overlay.png"))
                self._thumbs[i] = thumbnail_from_photo(d, overlay_png=png)
        try:
            write_report(self._report, self._rows, self._thumbs, **self._report_options)
        except OSError as exc:
            raise MonodbhError(f"{printable(self._report)}: cannot write the report "
                               f"({exc.strerror or exc})") from None

    def __enter__(self) -> "ResultWriter":
        return self

    def __exit__(self, *exc) -> None:
        if self._csv_file is not None and not self._csv_file.closed:
            self._csv_file.close()
