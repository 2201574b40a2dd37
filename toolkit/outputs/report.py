"""The HTML report of a batch: one self-contained file a person reads, offline, in any browser.

:func:`render_report` turns the batch's rows (the JSON dicts of
:class:`~monodbh.toolkit.result.MeasureResult`) and their overlay thumbnails into one HTML page
with everything inline (CSS, a small script, the pictures as ``data:`` JPEGs, the plots as SVG
drawn here), so it can be mailed or opened from a USB stick:

* the stand summary of the measured trees (:mod:`.stand`: trees, mean and quadratic mean DBH,
  basal area with its 1-sigma; per hectare when the plot's area is given) and how each photo's
  scale was set;
* a histogram of the DBH in 5 cm classes;
* a map-like scatter of the trees' positions (and the camera that saw each), north up, in
  metres around their centre, when any row has a position;
* a table of every photo, sortable by clicking a column heading (or with ``#sort=dbh_cm-desc``
  in the address): the overlay's thumbnail, DBH +- sigma, distance, scale source and flags in
  plain words, the retake advice where one applies, the error of a photo not measured, the
  field record.

The script marks the page once loaded: ``<body data-ready="1" data-rows=N data-thumbs=T
data-thumbs-loaded=L data-load-ms=MS>`` (used by the browser test). Imported by
:mod:`.results_file`; imports numpy, Pillow, OpenCV (thumbnails) and :mod:`.stand`.
"""
from __future__ import annotations

import base64
import html
import io
import math
import os
from datetime import datetime, timezone
from typing import Any, Iterable, Optional, Sequence

import numpy as np

from .atomic import atomic_write_text

__all__ = ["FLAG_TEXT", "SCALE_TEXT", "REPORT_THUMBNAIL_PX", "flag_text", "scale_text", "retake_advice",
           "thumbnail_jpeg", "thumbnail_from_photo", "render_report", "write_report"]

#: longest side of a photo's thumbnail in the report, pixels (about 10-25 kB as JPEG)
REPORT_THUMBNAIL_PX = 320
_JPEG_QUALITY = 72

#: flag -> what it means, in plain words (flags not listed are shown with spaces for underscores)
FLAG_TEXT = {
    "short_arc": "the stem's cross-section was seen over less than half its round",
    "low_inlier_ratio": "many stem points did not fit the circle",
    "estimators_disagree": "the DBH estimators disagree",
    "circle_as_check": "the circle fit was used as a check only",
    "few_pixels_across_stem": "the stem is only a few pixels wide: move closer",
    "scale_from_network": "the scale came from the depth network only (low confidence)",
    "distance_calibrated": "the network's distance was corrected by its measured bias",
    "scale_capped_by_visible_stem": "the distance was capped by the visible stem's length",
    "stem_base_from_network": "the stem's foot was found by the stem-base network",
    "stem_base_second_network": "the stem's foot was found by the second stem-base network (the first saw none)",
    "stem_base_from_user": "the stem's foot was tapped by the user",
    "stem_base_user_rejected": "the tapped foot is not below the marker: not used",
    "stem_base_occluded": "the stem's foot is hidden (bushes, another trunk)",
    "stem_base_edge": "the stem's foot is outside the photo",
    "stem_base_tracked": "the stem's foot was not recognised (its edges were followed down, which only bounds the distance)",
    "stem_base_above_visible_stem": ("what looked like the stem's foot is in front of it (the stem is seen lower): "
                                     "it only bounds the distance"),
    "stem_base_ambiguous": ("the stem-base network's foot moves lower when its strip is cut a little differently "
                            "(grass or a bush may hide the foot): the scale lies between the two, sigma widened"),
    "stem_base_lost": "the stem's edges could not be followed down to the foot",
    "stem_base_off_mask": "the stem's edges ran off the segmented trunk before the foot",
    "stem_base_unconfirmed": "no stem foot found (the stem-base network saw none; unconfirmed stem edges were not followed down)",
    "stem_base_ground": "the stem's foot was traced on the ground",
    "rope_too_thin_for_scale": "the marker is too thin in the photo to set the scale",
    "marker_not_read_for_scale": "the marker was found but its thickness could not be read",
    "rope_too_faint_for_scale": "the marker's edges are too faint to set the scale",
    "rope_read_at_full_resolution": "the marker's thickness was read on the full-resolution photo",
    "no_ground_plane": "no ground plane was found",
    "up_from_image": "'up' was taken from the photo's vertical lines",
    "photo_maybe_sideways": "the photo may be turned sideways (check its orientation)",
    "overlay_failed": "the overlay picture could not be written",
    "cloud_write_failed": "the point cloud could not be written",
    "tree_mask_from_rope": "the segmenter missed the roped stem; its outline came from the marker",
    "edge_at_rope_end": "one stem edge was taken at the marker's end (neighbouring trunk)",
    "edges_from_rope_band": "the stem edges were taken at the marker's ends (neighbouring trunk)",
    "edges_out_to_rope_end": "a stem edge was moved out to where the marker ends (outline inside the stem)",
    "edge_points_on_rope_end": "edge points on the marker's knot or loose ends were left out",
    "edges_from_network": "the stem-edge network moved a stem edge off a neighbour, shadow or background border",
    "width_disagrees_rope": "the stem edges are much wider or narrower than the marker across the stem: sigma widened",
    "rope_from_stem_profile": "the marker was found as a faint red row across the trunk",
    "rope_verified_by_network": "the faint marker was confirmed by the rope-verifier network",
    "rope_found_by_network": "the marker was found by the rope-finder network",
    "rope_chosen_by_network": "the rope-finder network chose the marker among red bands",
    "row_thinner_than_marker": "the tapped faint red row is much thinner than the marker would be at this distance",
    "trunk_segmented_at_tap": "the trunk at the tap was found by segmenting a close-up of it",
    "pick_on_rope_end": "the tap was on the marker's knot or loose end: the ring it hangs from was measured",
    "sigma_model_default": "no measured error model for these networks: built-in sigmas",
}

#: scale candidate -> plain words (a ``scale_source`` joins candidates with ``+``)
SCALE_TEXT = {
    "depth_gt": "true depth (evaluation)",
    "pose": "the marker's height over the ground (calibrated pose)",
    "stem_base_user": "the stem's foot (tapped)",
    "stem_base": "the stem's foot",
    "stem_base_weak": "the stem's foot (weak)",
    "ground_plane": "the ground plane",
    "rope_diameter": "the marker's width",
    "camera_height": "the camera's height",
    "network": "the depth network",
    "visible_stem": "the visible stem",
}

#: scale sources that are geometry (a known length in the scene), not the depth network
_GEOMETRIC = ("pose", "stem_base", "rope_diameter")


def flag_text(flag: str) -> str:
    """A flag in plain words (:data:`FLAG_TEXT`; ``scale_disagree_<source>`` spelled out)."""
    if flag in FLAG_TEXT:
        return FLAG_TEXT[flag]
    if flag.startswith("scale_disagree_"):
        return f"the scale from {scale_text(flag[len('scale_disagree_'):])} disagrees with the one used"
    return flag.replace("_", " ")


def scale_text(source: Optional[str]) -> str:
    """A ``scale_source`` such as ``"stem_base+network"`` in plain words (``""`` for None)."""
    if not source:
        return ""
    return " + ".join(SCALE_TEXT.get(p, p.replace("_", " ")) for p in str(source).split("+"))


def retake_advice(row: dict, marker_known: bool = False) -> str:
    """What to do about a row, or ``""``: how to retake a photo whose scale came from the depth
    network or whose stem is too small, what to check in one that may be wrong."""
    if row.get("error"):
        return ""
    flags = set(row.get("flags") or [])
    src = row.get("scale_source") or ""
    advice = []
    if not any(g in src for g in _GEOMETRIC):
        how = ("step back until the stem's foot is in the photo, or closer so that the marker is at "
               "least 5 px thick" if marker_known else
               "step back until the stem's foot is in the photo, or give the marker's width "
               "(dbh marker CAM --width-mm W, or --rope-mm W)")
        tap = ("" if flags & {"stem_base_edge", "stem_base_occluded"} else
               " Where the foot is in the photo but was not found, tap it: --base X,Y.")
        advice.append(f"Retake: {how}.{tap}")
    if "few_pixels_across_stem" in flags:
        advice.append("Retake closer: the stem is too few pixels wide.")
    if "photo_maybe_sideways" in flags:
        advice.append("Check the photo's orientation.")
    if "stem_base_ambiguous" in flags:
        advice.append("Check the stem's foot on the overlay: where grass or a bush hides it, tap the true foot "
                      "(--base X,Y).")
    if flags & {"width_disagrees_rope", "edges_from_rope_band", "edge_at_rope_end"}:
        advice.append("Check the overlay: a neighbouring trunk touches the stem, or its edges were taken on the bark.")
    return " ".join(advice)


# ------------------------------------------------------------------------------- thumbnails
def thumbnail_jpeg(rgb: np.ndarray, max_side: int = REPORT_THUMBNAIL_PX) -> bytes:
    """JPEG bytes of an RGB picture downscaled to ``max_side`` on its longest side.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
    max_side : int
        Longest side of the thumbnail, pixels (never upscaled).
    """
    import cv2
    from PIL import Image

    rgb = np.asarray(rgb)
    h, w = rgb.shape[:2]
    f = min(1.0, max_side / max(h, w))
    if f < 1.0:
        rgb = cv2.resize(rgb, (max(1, round(w * f)), max(1, round(h * f))), interpolation=cv2.INTER_AREA)
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb[..., :3]).astype(np.uint8)).save(
        buf, format="JPEG", quality=_JPEG_QUALITY, optimize=True)
    return buf.getvalue()


def thumbnail_from_photo(row: dict, max_side: int = REPORT_THUMBNAIL_PX,
                         overlay_png: Optional[str | os.PathLike] = None) -> Optional[bytes]:
    """The thumbnail of a row measured earlier (``--resume``): its overlay PNG when there is one,
    else its photo with the row's caption (:func:`~.overlay.render_overlay` without geometry);
    None when neither can be read."""
    try:
        if overlay_png is not None and os.path.isfile(overlay_png):
            from PIL import Image

            with Image.open(overlay_png) as im:
                return thumbnail_jpeg(np.asarray(im.convert("RGB")), max_side)
        from ..result import MeasureResult
        from .overlay import render_overlay

        res = MeasureResult(**{k: v for k, v in row.items() if k in MeasureResult.__dataclass_fields__})
        return thumbnail_jpeg(render_overlay(res), max_side)
    except Exception:  # noqa: BLE001 - the row is listed without a picture
        return None


# ------------------------------------------------------------------------------- figures
def _e(v: Any) -> str:
    return html.escape("" if v is None else str(v), quote=True)


def _num(v: Optional[float], nd: int = 1, unit: str = "") -> str:
    return "-" if v is None else f"{v:.{nd}f}{unit}"


def _stand(rows: Sequence[dict], plot_area_m2: Optional[float]):
    from .stand import PlotTrees, dbh_classes, summarise_plot

    ok = [r for r in rows if not r.get("error") and r.get("dbh_cm") is not None]
    d = np.array([float(r["dbh_cm"]) for r in ok], np.float64)
    s = np.array([math.nan if r.get("dbh_sigma_cm") is None else float(r["dbh_sigma_cm"]) for r in ok],
                 np.float64)
    summary = summarise_plot(PlotTrees(plot="batch", photos=len(rows), dbh_cm=d, dbh_sigma_cm=s), plot_area_m2)
    return summary, dbh_classes(d, plot_area_m2)


def _summary_html(summary, rows: Sequence[dict]) -> str:
    ba = f"{summary.basal_area_m2:.3f} &plusmn; {summary.basal_area_sigma_m2:.3f} m&sup2;"
    items = [("Photos", f"{summary.photos}"), ("Trees measured", f"{summary.trees}"),
             ("Not measured", f"{summary.not_measured}"),
             ("Mean DBH", "-" if summary.dbh_mean_cm is None else
              f"{summary.dbh_mean_cm:.1f} cm" + ("" if summary.dbh_mean_se_cm is None
                                                 else f" &plusmn; {summary.dbh_mean_se_cm:.1f} (s.e.)")),
             ("Quadratic mean DBH", _num(summary.dbh_quadratic_mean_cm, 1, " cm")),
             ("DBH range", "-" if summary.dbh_min_cm is None else
              f"{summary.dbh_min_cm:.1f} - {summary.dbh_max_cm:.1f} cm"),
             ("Basal area", ba)]
    if summary.area_m2 is not None:
        items += [("Plot area", f"{summary.area_m2:g} m&sup2;"),
                  ("Stems per hectare", f"{summary.stems_per_ha:.0f}"),
                  ("Basal area per hectare", f"{summary.basal_area_m2_per_ha:.2f} &plusmn; "
                                             f"{summary.basal_area_sigma_m2_per_ha:.2f} m&sup2;/ha")]
    ok = [r for r in rows if not r.get("error")]
    geo = sum(1 for r in ok if any(g in (r.get("scale_source") or "") for g in _GEOMETRIC))
    items += [("Scale from geometry", f"{geo} of {len(ok)}"),
              ("Scale from the depth network only", f"{len(ok) - geo} of {len(ok)}")]
    cells = "".join(f'<div class="kv"><span>{k}</span><b>{v}</b></div>' for k, v in items)
    return f'<section id="stand"><h2>Stand summary</h2><div class="grid">{cells}</div></section>'


def _histogram_svg(classes) -> str:
    """Bars of trees per 5 cm DBH class (``<rect class="bar">`` each)."""
    if not classes:
        return '<svg id="histogram" class="plot" viewBox="0 0 560 60" role="img"><text x="10" y="35">' \
               'no tree measured</text></svg>'
    W, H, left, bottom, top = 560, 260, 44, 40, 16
    n = len(classes)
    peak = max(c.trees for c in classes)
    step = max(1, math.ceil(peak / 5))
    ymax = step * math.ceil(peak / step)
    bw = (W - left - 10) / n
    out = [f'<svg id="histogram" class="plot" viewBox="0 0 {W} {H}" role="img" '
           f'aria-label="DBH histogram, {n} classes of 5 cm">']
    for t in range(0, ymax + 1, step):
        y = H - bottom - (H - bottom - top) * t / ymax
        out.append(f'<line x1="{left}" x2="{W - 10}" y1="{y:.1f}" y2="{y:.1f}" class="grid"/>'
                   f'<text x="{left - 6}" y="{y + 4:.1f}" text-anchor="end">{t}</text>')
    for i, c in enumerate(classes):
        h = (H - bottom - top) * c.trees / ymax
        x = left + i * bw
        out.append(f'<rect class="bar" data-class="{_e(c.dbh_class_cm)}" data-trees="{c.trees}" '
                   f'x="{x + 1:.1f}" y="{H - bottom - h:.1f}" width="{max(1.0, bw - 2):.1f}" height="{h:.1f}">'
                   f'<title>{_e(c.dbh_class_cm)} cm: {c.trees} trees</title></rect>')
        if n <= 16 or i % math.ceil(n / 16) == 0:
            out.append(f'<text x="{x + bw / 2:.1f}" y="{H - bottom + 14}" text-anchor="middle">'
                       f'{c.lower_cm:g}</text>')
    out.append(f'<text x="{(left + W) / 2:.0f}" y="{H - 6}" text-anchor="middle">DBH, cm (5 cm classes)</text>'
               f'<text x="12" y="{top + (H - bottom) / 2:.0f}" transform="rotate(-90 12 {top + (H - bottom) / 2:.0f})" '
               f'text-anchor="middle">trees</text></svg>')
    return "".join(out)


def _local_xy(lat: np.ndarray, lon: np.ndarray, lat0: float, lon0: float) -> tuple[np.ndarray, np.ndarray]:
    """East, north metres from ``(lat0, lon0)`` on the WGS 84 ellipsoid's local radii (a sketch's
    precision: well under 1 % over a plot)."""
    from .geo import WGS84_A, _E2

    phi = math.radians(lat0)
    w = 1.0 - _E2 * math.sin(phi) ** 2
    m = WGS84_A * (1 - _E2) / w ** 1.5          # meridional radius
    n = WGS84_A / math.sqrt(w)                  # prime vertical radius
    return np.radians(lon - lon0) * n * math.cos(phi), np.radians(lat - lat0) * m


def _map_svg(rows: Sequence[dict]) -> str:
    """Trees (circles sized by DBH) and the cameras that saw them, north up; '' without positions."""
    pts = [(i, r) for i, r in enumerate(rows) if not r.get("error") and r.get("tree_lat_deg") is not None
           and r.get("tree_lon_deg") is not None]
    if not pts:
        return ""
    tl = np.array([r["tree_lat_deg"] for _, r in pts], np.float64)
    tn = np.array([r["tree_lon_deg"] for _, r in pts], np.float64)
    cams = [(r.get("camera_lat_deg"), r.get("camera_lon_deg")) for _, r in pts]
    cl = np.array([np.nan if a is None else a for a, _ in cams], np.float64)
    cn = np.array([np.nan if b is None else b for _, b in cams], np.float64)
    lat0, lon0 = float(np.mean(tl)), float(np.mean(tn))
    tx, ty = _local_xy(tl, tn, lat0, lon0)
    cx, cy = _local_xy(cl, cn, lat0, lon0)
    allx = np.concatenate([tx, cx[np.isfinite(cx)]])
    ally = np.concatenate([ty, cy[np.isfinite(cy)]])
    span = max(10.0, float(np.ptp(allx)), float(np.ptp(ally))) * 1.1
    mx, my = (allx.max() + allx.min()) / 2, (ally.max() + ally.min()) / 2
    S, pad = 520, 30
    k = (S - 2 * pad) / span

    def px(x, y):
        return pad + (S - 2 * pad) / 2 + (x - mx) * k, pad + (S - 2 * pad) / 2 - (y - my) * k

    out = [f'<svg id="map" class="plot" viewBox="0 0 {S} {S + 20}" role="img" '
           f'aria-label="tree positions, north up, {len(pts)} trees">'
           f'<rect x="1" y="1" width="{S - 2}" height="{S - 2}" class="frame"/>']
    for j, (i, r) in enumerate(pts):
        X, Y = px(tx[j], ty[j])
        if np.isfinite(cx[j]):
            CX, CY = px(cx[j], cy[j])
            out.append(f'<line class="sight" x1="{CX:.1f}" y1="{CY:.1f}" x2="{X:.1f}" y2="{Y:.1f}"/>'
                       f'<circle class="camera" cx="{CX:.1f}" cy="{CY:.1f}" r="2.5"/>')
        rad = max(3.0, float(r["dbh_cm"]) / 100.0 / 2 * k) if r.get("dbh_cm") is not None else 3.0
        label = r.get("tag") or os.path.basename(str(r.get("photo", "")))
        out.append(f'<a href="#row-{i}"><circle class="tree" data-photo="{_e(r.get("photo"))}" cx="{X:.1f}" '
                   f'cy="{Y:.1f}" r="{rad:.1f}"><title>{_e(label)}: DBH {_num(r.get("dbh_cm"))} cm</title>'
                   f'</circle></a>')
    # scale bar: a round length near a fifth of the span
    bar = 10 ** math.floor(math.log10(span / 5))
    for m in (5, 2, 1):
        if m * bar <= span / 4:
            bar *= m
            break
    out.append(f'<line class="scalebar" x1="{pad}" x2="{pad + bar * k:.1f}" y1="{S - 14}" y2="{S - 14}"/>'
               f'<text x="{pad}" y="{S - 20}">{bar:g} m</text>'
               f'<text x="{S - 24}" y="26" text-anchor="middle" class="north">N</text>'
               f'<path d="M{S - 24} 30 l-6 14 l6 -4 l6 4 z" class="north"/>'
               f'<text x="{pad}" y="{S + 14}">centre {lat0:.6f}, {lon0:.6f} (WGS 84); grey: the cameras</text></svg>')
    return "".join(out)


# ------------------------------------------------------------------------------- the table
_COLUMNS = (("n", "#", "num"), ("photo", "Photo", "text"), ("dbh_cm", "DBH, cm", "num"),
            ("distance_m", "Distance, m", "num"), ("scale_source", "Scale from", "text"),
            ("flags", "Flags", "text"), ("advice", "Advice / error", "text"),
            ("taken_at", "Taken at", "text"), ("position", "Tree position", "text"))


def _row_html(i: int, r: dict, thumb: Optional[bytes], marker_known: bool) -> str:
    err = r.get("error")
    name = os.path.basename(str(r.get("photo", "")))
    img = ""
    if thumb:
        img = (f'<img class="thumb" alt="overlay of {_e(name)}" '
               f'src="data:image/jpeg;base64,{base64.b64encode(thumb).decode("ascii")}">')
    tag = r.get("tag")
    photo = (f'{img}<div class="name" title="{_e(r.get("photo"))}">{_e(name)}</div>'
             + (f'<div class="tag">tag {_e(tag)}</div>' if tag and tag != os.path.splitext(name)[0] else ""))
    dbh = r.get("dbh_cm")
    dbh_cell = ("-" if dbh is None else
                f'<b>{dbh:.1f}</b>' + ("" if r.get("dbh_sigma_cm") is None else f' &plusmn; {r["dbh_sigma_cm"]:.1f}'))
    flags = r.get("flags") or []
    flags_cell = "".join(f'<li title="{_e(f)}">{_e(flag_text(f))}</li>' for f in flags)
    advice = _e(err) if err else _e(retake_advice(r, marker_known))
    lat, lon = r.get("tree_lat_deg"), r.get("tree_lon_deg")
    pos = "" if lat is None or lon is None else f"{lat:.6f}, {lon:.6f}"
    cls = ' class="failed"' if err else (' class="weak"' if retake_advice(r, marker_known) else "")
    vals = {"n": i + 1, "photo": name, "dbh_cm": "" if dbh is None else dbh,
            "distance_m": "" if r.get("distance_m") is None else r["distance_m"],
            "scale_source": r.get("scale_source") or "", "flags": len(flags), "advice": err or "",
            "taken_at": r.get("taken_at") or "", "position": pos}
    cells = {"n": str(i + 1), "photo": photo, "dbh_cm": dbh_cell,
             "distance_m": _num(r.get("distance_m"), 2), "scale_source": _e(scale_text(r.get("scale_source"))),
             "flags": f"<ul>{flags_cell}</ul>" if flags_cell else "", "advice": advice,
             "taken_at": _e(r.get("taken_at") or ""), "position": pos}
    tds = "".join(f'<td data-v="{_e(vals[k])}">{cells[k]}</td>' for k, _, _ in _COLUMNS)
    return f'<tr id="row-{i}" data-photo="{_e(r.get("photo"))}"{cls}>{tds}</tr>'


_CSS = """
body{font:14px/1.4 system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0 auto;max-width:1280px;
padding:12px 20px;color:#1b1b1b;background:#fff}
h1{font-size:22px;margin:8px 0 2px}h2{font-size:17px;margin:22px 0 8px}.meta{color:#555;font-size:13px}
.grid{display:grid;grid-template-columns:repeat(auto-fill,minmax(230px,1fr));gap:6px 18px}
.kv{display:flex;justify-content:space-between;border-bottom:1px solid #e4e4e4;padding:3px 0}
.kv span{color:#555}.plots{display:flex;flex-wrap:wrap;gap:24px}.plots>div{flex:1 1 460px;max-width:600px}
.plot{width:100%;height:auto}
.plot text{font-size:11px;fill:#333}.plot .grid{stroke:#e0e0e0}.bar{fill:#2e7d32}.frame{fill:#f6f9f4;stroke:#bbb}
.tree{fill:#2e7d32;fill-opacity:.75;stroke:#124d16}.camera{fill:#888}.sight{stroke:#aaa;stroke-dasharray:3 3}
.scalebar{stroke:#222;stroke-width:3}.north{fill:#222;font-weight:bold;font-size:14px}
table{border-collapse:collapse;width:100%;font-size:13px}th,td{border-bottom:1px solid #e4e4e4;padding:4px 6px;
vertical-align:top;text-align:left}th{position:sticky;top:0;background:#f3f3f3;cursor:pointer;user-select:none;
white-space:nowrap}th.asc::after{content:" \\25B2"}th.desc::after{content:" \\25BC"}
td ul{margin:0;padding-left:14px;font-size:12px;max-width:300px}tr.failed td{background:#fdecec}tr.failed td:nth-child(7){color:#b00020}
tr.weak td:nth-child(7){color:#8a5a00}img.thumb{display:block;width:160px;height:auto;border:1px solid #ccc;
cursor:zoom-in}img.thumb.big{width:320px;cursor:zoom-out}.name{font-family:ui-monospace,monospace;
font-size:12px;word-break:break-all;max-width:170px}.tag{color:#555;font-size:12px}
@media print{th{position:static}img.thumb{width:120px}}
"""

_JS = """
(function(){
var table=document.getElementById('photos'),body=table.tBodies[0];
function sortBy(key,dir){var ths=table.tHead.rows[0].cells,col=-1,num=false;
for(var i=0;i<ths.length;i++){ths[i].classList.remove('asc','desc');if(ths[i].dataset.key===key){col=i;
num=ths[i].dataset.type==='num';ths[i].classList.add(dir);}}
if(col<0)return;var rows=Array.prototype.slice.call(body.rows);
rows.sort(function(a,b){var x=a.cells[col].dataset.v,y=b.cells[col].dataset.v,r;
if(num){var fx=x===''?NaN:+x,fy=y===''?NaN:+y;if(isNaN(fx)&&isNaN(fy))r=0;else if(isNaN(fx))return 1;
else if(isNaN(fy))return -1;else r=fx-fy;}else r=x.localeCompare(y);
if(r===0)r=(+a.cells[0].dataset.v)-(+b.cells[0].dataset.v);return dir==='desc'?-r:r;});
rows.forEach(function(r){body.appendChild(r);});document.body.dataset.sortedBy=key+'-'+dir;}
Array.prototype.forEach.call(table.tHead.rows[0].cells,function(th){th.addEventListener('click',function(){
var dir=th.classList.contains('asc')?'desc':'asc';sortBy(th.dataset.key,dir);
history.replaceState(null,'','#sort='+th.dataset.key+'-'+dir);});});
body.addEventListener('click',function(e){if(e.target.classList.contains('thumb'))e.target.classList.toggle('big');});
var m=/#sort=([a-z_]+)-(asc|desc)/.exec(location.hash);if(m)sortBy(m[1],m[2]);
window.addEventListener('load',function(){var imgs=document.querySelectorAll('img.thumb'),ok=0;
for(var i=0;i<imgs.length;i++){if(imgs[i].complete&&imgs[i].naturalWidth>0)ok++;}
var d=document.body.dataset;d.rows=body.rows.length;d.thumbs=imgs.length;d.thumbsLoaded=ok;
d.bars=document.querySelectorAll('#histogram rect.bar').length;
d.mapTrees=document.querySelectorAll('#map circle.tree').length;
d.loadMs=Math.round(performance.now());d.ready='1';});
})();
"""


def render_report(rows: Sequence[dict], thumbnails: Optional[Sequence[Optional[bytes]]] = None, *,
                  title: str = "monodbh report", meta: Optional[dict] = None,
                  plot_area_m2: Optional[float] = None, marker_known: bool = False,
                  generated_at: Optional[datetime] = None) -> str:
    """The report's HTML (one self-contained page; see the module docstring).

    Parameters
    ----------
    rows : sequence of dict
        The batch's rows in input order, JSON dicts of ``MeasureResult`` (printable strings).
    thumbnails : sequence of bytes or None, optional
        A JPEG per row (None: no picture).
    title : str
    meta : dict, optional
        Lines of the header, label -> value (e.g. the camera file, the marker's width).
    plot_area_m2 : float, optional
        The plot's horizontal area, m^2: per-hectare figures.
    marker_known : bool
        The marker's width was known (changes the retake advice).
    generated_at : datetime, optional
        Time written in the header (default now, UTC).

    Returns
    -------
    str
        HTML5 text.

    Examples
    --------
    >>> page = render_report([{"photo": "a.jpg", "dbh_cm": 31.2, "dbh_sigma_cm": 1.1,
    ...                        "scale_source": "stem_base", "flags": []}])
    >>> 'data-photo="a.jpg"' in page
    True
    """
    rows = list(rows)
    thumbs = list(thumbnails) if thumbnails is not None else [None] * len(rows)
    if len(thumbs) != len(rows):
        raise ValueError(f"{len(thumbs)} thumbnails for {len(rows)} rows")
    summary, classes = _stand(rows, plot_area_m2)
    when = (generated_at or datetime.now(timezone.utc)).strftime("%Y-%m-%d %H:%M UTC")
    meta_html = " &middot; ".join(f"{_e(k)}: {_e(v)}" for k, v in (meta or {}).items() if v is not None)
    map_svg = _map_svg(rows)
    heads = "".join(f'<th data-key="{k}" data-type="{t}">{_e(label)}</th>' for k, label, t in _COLUMNS)
    body = "\n".join(_row_html(i, r, thumbs[i], marker_known) for i, r in enumerate(rows))
    plots = (f'<div><h2>DBH distribution</h2>{_histogram_svg(classes)}</div>'
             + (f'<div><h2>Tree positions</h2>{map_svg}</div>' if map_svg else ""))
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
            f'<meta name="viewport" content="width=device-width,initial-scale=1">'
            f'<title>{_e(title)}</title><style>{_CSS}</style></head>\n<body>'
            f'<h1>{_e(title)}</h1><div class="meta">{len(rows)} photos &middot; generated {when}'
            f'{" &middot; " + meta_html if meta_html else ""}</div>\n'
            f'{_summary_html(summary, rows)}\n<section class="plots">{plots}</section>\n'
            f'<section><h2>Photos</h2><p class="meta">Click a heading to sort, a picture to enlarge it. '
            f'Flags and scale in plain words; hover a flag for its name in the CSV.</p>'
            f'<table id="photos"><thead><tr>{heads}</tr></thead><tbody>\n{body}\n</tbody></table></section>\n'
            f'<script>{_JS}</script></body></html>\n')


def write_report(path: str | os.PathLike, rows: Iterable[dict],
                 thumbnails: Optional[Sequence[Optional[bytes]]] = None, **kw: Any) -> str:
    """Write :func:`render_report` to ``path`` atomically; returns the HTML."""
    page = render_report(list(rows), thumbnails, **kw)
    atomic_write_text(path, page)
    return page
