"""From perception (rope, stem mask, ground, depth, silhouette depth) to a metric DBH.

This module is pure geometry on numpy arrays. The same code runs on network outputs
(:mod:`.pipeline`) and on ground-truth perception (``dbh eval --gt-perception``, the
single-view floor), so the two are directly comparable.

Method (see README "How the scale is set"):

1. Silhouette edges of the stem just above and below the rope, to a fraction of a pixel
   (:func:`~.edges.trunk_edges`) -> tangent rays ``r_L``, ``r_R``; their bisector ``r_A``
   passes through the stem axis.
2. The stem direction ``v``: the "up" direction (from the calibrated pose when cam.yaml has
   one, else the normal of the ground plane fitted by RANSAC to the depth map's ground
   points), constrained to the plane through the camera centre and the stem's image mid-line.
3. Metric scale. The rope is 1.3 m along the stem above the ground; candidate sources:
   ``pose`` (camera height + pitch/roll from cam.yaml, with the stem base),
   ``ground_plane`` (rope height above the depth map's RANSAC ground plane -> rescale),
   ``stem_base`` (single-view metrology between the rope and the visible stem base, traced
   down the stem mask), ``stem_base_user`` (the same with the base pixel the user tapped,
   ``dbh measure --base X,Y``), and
   ``network`` (the depth network's own metric output; weakest). Each gives the axis depth
   with a standard deviation; the source with the least typical error leads and those that
   agree with it are averaged in. Where the stem is followed down from the rope to something
   that hides it (grass, a bush), the base is at or below that point: the metrology through it
   bounds the distance from above, and a network scale beyond it is capped (``visible_stem``).
4. DBH: ``tangent`` = ``2 D sin(alpha / 2)`` from the tangent rays; ``cloud`` = circle fitted
   (RANSAC + geometric refinement) to the front and back surface points of the stem slice
   (silhouette depth map). Combined by inverse-variance weighting, with a 1-sigma that
   includes the single-view ovality term.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .edges import REASON_OUT_OF_PHOTO, trace_stem_base, track_stem_base, trunk_edges
from .geometry import (fit_circle, fit_plane_ransac, metrology_distance, normalize,
                       project_perpendicular, rays_from_normalized, tangent_diameter)
from .result import MeasureResult

__all__ = ["Perception", "measure_from_perception", "SIGMA_MODEL"]

ROPE_HEIGHT_M = 1.3

#: Relative 1-sigma error terms of the DBH (fractions), calibrated on the synthetic
#: validation set (seeds 2000.., never the benchmark): ``ovality`` is the single-view floor
#: (one view sees one width of a stem that is not round).
SIGMA_MODEL = dict(ovality=0.030, edge_px=0.35, pose=0.02, ground_plane=0.035, stem_base=0.04,
                   network=0.15, cloud_extra=0.05, ground_plane_network=0.30, camera_height=0.20)
#: with network perception (coarse masks, network depth) the same sources are much less certain:
#: relative 1-sigma errors measured on 27 measured roped photos of the development bench (seed
#: 9000, photos 0-39; median |log error| / 0.674): network depth 0.25 -> 0.37, ground plane
#: from network depth 0.32 -> 0.47, camera-height prior 0.31 -> 0.46, stem base from predicted
#: masks (2 of 2 wrong) 0.5; stem width from mask-guided edges 0.096 -> 0.14; silhouette-net
#: circle 0.19 -> 0.28 (and biased +14 %)
SIGMA_MODEL_NETWORK = dict(network=0.37, ground_plane_network=0.47, camera_height=0.46, stem_base=0.50, stem_base_weak=0.50,
                           pose=0.05, width=0.14, cloud=0.28, stem_base_user=0.06, rope_diameter=0.12)
#: which "up" direction is used, best first: the calibrated pose, the vertical vanishing point
#: of trunk edges, the depth network's ground plane, the stem's image direction
UP_PRIORITY = ("pose", "vanishing", "ground_plane", "image")
#: a stem edge width more than this factor beyond the rope band's length is flagged
#: (``width_disagrees_rope``) and the gap added to the DBH sigma
ROPE_WIDTH_RATIO_MAX = 1.3
#: the rope check of the edges (:func:`_edges_checked_by_rope`): a side's mask edge lying beyond
#: the rope's end by more than ``max(ROPE_GAP_MIN_PX, ROPE_GAP_MIN_FRACTION x band width)``,
#: where the rope's row is less than ``ROPE_GAP_MAX_RATIO`` as red (against its neighbouring
#: rows) as on the rope itself, is replaced by the edge at the rope's end. Set on the calibration
#: sets (seeds 9100, 9200; 118 measured photos): the tangent DBH at the true distance 2.49 ->
#: 2.24 cm MAE; benchmark (seed 9000) 2.88 -> 2.37 cm.
ROPE_GAP_MIN_PX = 3.0
ROPE_GAP_MIN_FRACTION = 0.04
ROPE_GAP_MAX_RATIO = 0.2
#: ... applied only where the rope itself stands out this much (red-ness contrast)
ROPE_GAP_MIN_CONTRAST = 0.02
#: the rope as a ruler (``--rope-mm``): its thickness across the band (the rope detector's full
#: width at half maximum of the red-ness profile) is trusted from this many pixels on, where its
#: mean profile's red-ness contrast is at least ROPE_RULER_MIN_CONTRAST. Measured on the
#: calibration sets (seeds 9100, 9200) against the true ``f D / z`` of the rope's front: from 5 px
#: on, median log ratio -0.058 (ROPE_RULER_FWHM_RATIO: the shaded flanks of the tube are less
#: red), MAD 0.072; at 4-5 px +0.18, at 3-4 px +0.10 with MAD 0.20 (blur widens thin ropes). The 3
#: ropes of 5 px or more measured 2.5-4.7x too thick (calibration sets and benchmark) were all
#: faint (contrast 0.042-0.070; 95 % of the others above 0.11).
ROPE_RULER_MIN_PX = 5.0
ROPE_RULER_MIN_CONTRAST = 0.09
ROPE_RULER_FWHM_RATIO = 0.944
#: scale sources precise enough (a few per cent) that the tangent estimate alone sets the DBH
#: with network perception (see measure_from_perception)
PRECISE_SCALE_SOURCES = ("pose", "stem_base_user", "stem_base", "stem_base_weak")
#: the stem-base network's bases with a probability under this are the source "stem_base_weak"
#: (its own measured sigma); measured on the calibration photos: 25 bases at p >= 0.5 were 1.9 %
#: off (median), the 11 at 0.3-0.5 5.5 % (mean) with more outliers on the benchmark
BASE_P_STRONG = 0.5
#: scale sources that come from the depth network (their distances get the error model's
#: calibration, ``Perception.distance_calibration``)
NETWORK_SCALE_SOURCES = ("network", "ground_plane", "camera_height")
#: a scale more than this fraction beyond the visible stem's bound is capped to the bound
SCALE_BOUND_SLACK = 0.03
#: how the network depth of the roped stem is read at the rope: "nearest" (the minimum across
#: the stem between its edges, :func:`_depth_nearest_across`) or "centre" (the median of three
#: points in the stem's middle, before session 14). At the stem's centre the network's depth is
#: too far by a margin that grows as the stem thins (background bleeding through the 256-pixel
#: map): median ln error +0.24 for stems 15-30 px wide at fx 1000, +0.12 at 30-60, +0.03 wider
#: (roped stems of calibration sets 9100, 9200 and the benchmark, 244 points, true masks); the
#: nearest depth across the stem: bias +0.01 and rms 0.278 -> 0.247 (seed 9100), 0.278 -> 0.253
#: (9200), 0.253 -> 0.243 (benchmark). The median of such reads at 8 cross-sections within a
#: stem width above and below the rope was no better (calibration sets 9100-9300: network rms
#: 0.296 -> 0.290) and worse on the benchmark (DBH MAE 5.37 -> 5.70 cm).
STEM_DEPTH_READ = "nearest"
#: the stem-base tracker's outcomes whose lowest tracked point bounds the distance: "occluded"
#: (something hides the stem below it). Not "edge" (the photo's border; measured loose: median
#: 2.2x the true distance, never under the network's, calibration sets 9100-9300) nor "lost"
#: (5.3x), nor "off_mask" (the edges ran on past the mask's end: tight, median 1.10x, but 2 of 11
#: more than 4 % under the truth; capping there helped 3 calibration photos and made both
#: benchmark photos it changed worse, MAE 5.44 -> 5.51 cm).
SCALE_BOUND_STATUSES = ("occluded",)
#: how the stem base is found when the user gives none: "edges" (silhouette edges followed down
#: to the ground, :func:`~.edges.track_stem_base`), "mask" (the tree mask traced down, session 4),
#: "either" (edges, else the mask). Measured on the calibration photos: the edges found 9 bases
#: in 160 (seeds 9100, 9200), all within 13 % in scale (median 3.5 %); on seed 9100 the mask
#: tracer found 8, 3 of them off by a factor 1.3-8.
BASE_FINDER = "edges"
#: run the stem-base network also where the edge tracker is not used (the segmenter missed the
#: stem, or the edges are much wider than the rope). Off: on the benchmark the one photo where it
#: then set the scale (a rope-band mask) had its DBH 22.6 cm off through the stem's width, which
#: with a precise scale is the tangent estimate alone
BASE_NETWORK_UNCONFIRMED = False
#: scale-candidate name -> its key in the network error model (SIGMA_MODEL_NETWORK, manifest)
_SN_KEY = {"ground_plane": "ground_plane_network"}
#: typical height of a handheld phone above the ground (the scale prior "camera_height")
CAMERA_HEIGHT_PRIOR_M = 1.5


@dataclass
class Perception:
    """Everything the geometry needs, in one image frame (the "working" image).

    Attributes
    ----------
    rgb : (H, W, 3) uint8 photo (possibly downscaled).
    camera : monodbh.calib.Camera for exactly this image size.
    rope_xy : (2,) rope centre on the stem; rope_dir : (2,) band direction across the stem.
    rope_half_px : half thickness of the rope band.
    tree_mask : (H, W) bool roped stem's instance mask.
    ground_mask : (H, W) bool ground pixels.
    depth : (H, W) float32 z-depth (metres, possibly wrongly scaled) or None.
    depth_job : or a handle whose ``.result()`` gives ``depth`` (the depth network running on
        another thread): waited for only where the depth is first needed, after the steps that
        do not need it (stem edges, vanishing point); the wait is ``timings_ms["depth"]``.
    depth_is_metric : whether ``depth`` is trusted as metric (ground truth).
    z1, z2 : (H, W) float32 front/back surface depth of the roped tree (same units as
        ``depth``; 0 outside) or None.
    source : "network" or "ground_truth".
    """
    rgb: np.ndarray
    camera: object
    rope_xy: np.ndarray
    rope_dir: np.ndarray
    rope_half_px: float
    tree_mask: np.ndarray
    ground_mask: np.ndarray
    depth: np.ndarray | None = None
    depth_is_metric: bool = False
    depth_job: object = None        # handle whose .result() is ``depth`` (computed elsewhere), taken at first need
    z1: np.ndarray | None = None
    z2: np.ndarray | None = None
    source: str = "network"
    silhouette_fn: object = None    # callable(z_axis_m, edges) -> (z1, z2) maps in metres, or None
    edge_search_px: float = 3.0     # how far from the mask border trunk edges are searched (pixels)
    edge_mask: np.ndarray | None = None  # (H, W) bool mask guiding the edge search (default tree_mask)
    base_xy: np.ndarray | None = None   # (2,) stem base pixel given by the user (front contact with the ground)
    base_finder: object = None      # callable(rgb, top_xy, along, width_px) -> BaseEstimate (the stem-base network) or None
    rope_length_px: float | None = None  # length of the rope band across the stem (pixels)
    rope_band_mask: np.ndarray | None = None  # (H, W) bool band as wide as the rope's extent
    rope_thickness_px: float | None = None  # the rope's measured thickness (FWHM across the band, pixels)
    rope_thickness_native_px: float | None = None  # the same in the pixels it was measured in (full resolution)
    rope_contrast: float | None = None      # red-ness contrast of the rope's mean profile across the band
    rope_diameter_m: float | None = None    # the rope's true diameter, given by the user (``--rope-mm``)
    use_vanishing: bool = True      # estimate "up" from the vertical vanishing point (no pose)
    sigma_network: dict | None = None  # measured error model of the shipped networks (manifest)
    rank_network: dict | None = None   # their typical errors, which pick the leading scale source
    distance_calibration: dict | None = None  # {"a", "b", "sigma"}: ln d -> a + b ln d for network-led scales
    extra: dict = field(default_factory=dict)


def _edges_two_pass(gray, mask, perc):
    """Trunk edges at the rope guided by ``mask``; a second pass samples across the stem as
    found (the rope band may be tilted or arced)."""
    edges = trunk_edges(gray, mask, perc.rope_xy, perc.rope_dir, rope_half_px=perc.rope_half_px,
                        search_px=perc.edge_search_px)
    if edges:
        across = np.array([edges.along[1], -edges.along[0]])
        mid0 = 0.5 * (edges.left_xy + edges.right_xy)
        e2 = trunk_edges(gray, mask, mid0, across, rope_half_px=perc.rope_half_px,
                         search_px=perc.edge_search_px)
        if e2 and abs(e2.width_px / edges.width_px - 1) < 0.5:
            edges = e2
    return edges


def _edges_checked_by_rope(gray, perc, edges):
    """Check each side of the mask-guided ``edges`` against the rope (see ROPE_GAP_*).

    The rope is tied round the roped stem only: where the mask's edge lies well beyond the end of
    the rope band and the rope's row there is no redder than the rows beside it, the mask has
    taken in a neighbouring trunk (or background) and that side's edge is searched at the rope's
    end instead. Where the rope goes on (faintly, e.g. in the stem's shade), the mask's edge stays.

    Returns
    -------
    (edges, n_sides): the checked edges and how many sides were replaced (0-2).
    """
    from .edges import combine_edges, rope_row_contrast
    from .rope import redness_map
    e3 = _edges_two_pass(gray, perc.rope_band_mask, perc)
    if not e3:
        return edges, 0
    c = np.asarray(perc.rope_xy, np.float64)
    u, a = edges.across, edges.along
    sL1, sR1 = float((edges.left_xy - c) @ u), float((edges.right_xy - c) @ u)
    sL3, sR3 = float((e3.left_xy - c) @ u), float((e3.right_xy - c) @ u)
    w3 = sR3 - sL3
    gap_min = max(ROPE_GAP_MIN_PX, ROPE_GAP_MIN_FRACTION * w3)
    gaps = {"left": sL3 - sL1, "right": sR1 - sR3}
    if w3 <= 4 or max(gaps.values()) <= gap_min:
        return edges, 0
    # red-ness in a window around the stem only
    h = max(0.5, float(perc.rope_half_px))
    sag = 0.05 * w3
    m = int(np.ceil(max(abs(sL1), abs(sR1)) + 6 * h + 8 + sag))
    H, W = gray.shape
    x0, y0 = max(0, int(c[0]) - m), max(0, int(c[1]) - m)
    x1, y1 = min(W, int(c[0]) + m + 1), min(H, int(c[1]) + m + 1)
    F = redness_map(np.ascontiguousarray(perc.rgb[y0:y1, x0:x1]))
    c_loc = c - (x0, y0)

    def contrast(lo, hi):
        ss = np.arange(lo, hi, 0.5)
        if len(ss) < 3:
            return np.nan
        return float(np.median(rope_row_contrast(F, c_loc, perc.rope_dir, u, a, ss, rope_half_px=h, sag_px=sag)))

    c_in = contrast(sL3 + 0.15 * w3, sR3 - 0.15 * w3)
    if not c_in > ROPE_GAP_MIN_CONTRAST:
        return edges, 0
    left, right, n = edges, edges, 0
    if gaps["left"] > gap_min and contrast(sL1 + 1, sL3 - 1) < ROPE_GAP_MAX_RATIO * c_in:
        left, n = e3, n + 1
    if gaps["right"] > gap_min and contrast(sR3 + 1, sR1 - 1) < ROPE_GAP_MAX_RATIO * c_in:
        right, n = e3, n + 1
    if n == 0:
        return edges, 0
    return (e3 if n == 2 else combine_edges(left, right, frame=edges)), n


#: weight of the stem edges' own direction against the vertical through the vanishing point (or
#: the pose) in the stem's image direction below the rope. Measured on the calibration photos
#: (106): edges alone 1.64 deg from the true axis (median; 90th percentile 5.95), the vertical
#: alone 1.41 (4.47), 0.3 x edges + 0.7 x vertical 1.28 (3.89).
STEM_DIRECTION_EDGE_WEIGHT = 0.3


def _stem_image_direction(cam, mid_xy, along, up_sources) -> np.ndarray:
    """(2,) unit image direction down the stem at ``mid_xy``: the edges' ``along`` blended with
    the image of the vertical through ``mid_xy`` (towards the vertical vanishing point) when the
    pose or the vanishing point gives "up" (see :data:`STEM_DIRECTION_EDGE_WEIGHT`)."""
    a = np.asarray(along, np.float64)
    a = a / np.linalg.norm(a)
    up = up_sources.get("pose", up_sources.get("vanishing"))
    if up is None:
        return a
    K = np.asarray(cam.K, np.float64)
    x = np.linalg.solve(K, np.array([mid_xy[0], mid_xy[1], 1.0]))
    up = np.asarray(up, np.float64)
    if up[1] > 0:
        up = -up
    y = x - 0.02 * up
    if y[2] <= 1e-6:
        return a
    p = K @ y
    d = p[:2] / p[2] - np.asarray(mid_xy, np.float64)
    n = float(np.linalg.norm(d))
    if not n > 0:
        return a
    d = d / n
    if d @ a < 0:
        d = -d
    b = STEM_DIRECTION_EDGE_WEIGHT * a + (1 - STEM_DIRECTION_EDGE_WEIGHT) * d
    return b / np.linalg.norm(b)


def _rays(camera, xy):
    nxy = camera.undistort_points(np.asarray(xy, np.float64).reshape(-1, 2), normalized=True)
    return rays_from_normalized(nxy)


def _depth_at(depth, mask, xy, radius):
    H, W = depth.shape
    x, y = int(round(xy[0])), int(round(xy[1]))
    r = int(max(1, radius))
    win = depth[max(0, y - r):y + r + 1, max(0, x - r):x + r + 1]
    m = mask[max(0, y - r):y + r + 1, max(0, x - r):x + r + 1] & (win > 0)
    if not m.any():
        return np.nan
    return float(np.median(win[m]))


def _depth_nearest_across(depth, left_xy, right_xy, rows: int = 2, inner: float = 0.9):
    """The nearest depth on the stem's cross-section: the minimum of ``depth`` (H, W) over the
    segment between the two edge points (its middle ``inner`` fraction), ``+-rows`` pixels
    across it; nan where nothing positive is there.

    The depth network's map is upsampled from its 256-pixel input, where a thin stem is a few
    pixels wide: the background behind it bleeds into its middle, so the middle reads too far
    (see :data:`STEM_DEPTH_READ`).
    """
    H, W = depth.shape
    L = np.asarray(left_xy, np.float64)
    d = np.asarray(right_xy, np.float64) - L
    n = max(2, int(np.ceil(np.linalg.norm(d))) + 1)
    f = 0.5 + (np.linspace(0.0, 1.0, n) - 0.5) * inner
    P = L[None] + f[:, None] * d[None]
    across = np.array([-d[1], d[0]]) / (np.linalg.norm(d) + 1e-12)
    best = np.inf
    for k in range(-rows, rows + 1):
        Q = np.round(P + k * across).astype(int)
        ok = (Q[:, 0] >= 0) & (Q[:, 0] < W) & (Q[:, 1] >= 0) & (Q[:, 1] < H)
        if ok.any():
            z = depth[Q[ok, 1], Q[ok, 0]]
            z = z[z > 0]
            if z.size:
                best = min(best, float(z.min()))
    return best if np.isfinite(best) else np.nan


def _ground_plane(perc: Perception, edges, up_hint):
    """RANSAC plane on depth-map ground points around the stem base region."""
    depth = perc.depth
    H, W = depth.shape
    g = perc.ground_mask & (depth > 0)
    ys, xs = np.nonzero(g)
    if len(xs) < 50:
        return None, "too few ground pixels"
    c = np.asarray(perc.rope_xy)
    wpx = max(edges.width_px, 4.0)
    # prefer ground within a generous window around and below the stem
    near = (np.abs(xs - c[0]) < max(12 * wpx, 0.25 * W)) & (ys > c[1] - 0.05 * H)
    if near.sum() >= 200:
        xs, ys = xs[near], ys[near]
    if len(xs) > 4000:
        sel = np.random.default_rng(0).choice(len(xs), 4000, replace=False)
        xs, ys = xs[sel], ys[sel]
    z = depth[ys, xs].astype(np.float64)
    nxy = perc.camera.undistort_points(np.c_[xs, ys].astype(np.float64), normalized=True)
    P = np.c_[nxy * z[:, None], z]
    zt = _depth_at(depth, perc.tree_mask, c, 3)
    thr = 0.02 * (zt if np.isfinite(zt) else np.median(z)) + 0.01
    pl = fit_plane_ransac(P, threshold=thr)
    if not pl:
        return None, pl.reason
    if up_hint is not None and pl.n @ up_hint < 0.7:
        return None, "ground plane not level"
    return pl, ""


def stem_edges(perc: Perception, gray: np.ndarray):
    """The roped stem's silhouette edges at the rope, checked against the rope band.

    Parameters
    ----------
    perc : :class:`Perception` (its edge mask, rope and rope band are used).
    gray : (H, W) float32 intensity of ``perc.rgb``.

    Returns
    -------
    (edges, flags, width_vs_rope): :class:`~.edges.TrunkEdges` (falsy with a reason when not
    found), the flags this step raised, and ``|ln(edge width / rope length)|`` when the two
    disagree (a sigma term, else 0).
    """
    emask = perc.tree_mask if perc.edge_mask is None else perc.edge_mask
    edges = _edges_two_pass(gray, emask, perc)
    flags: list[str] = []
    width_vs_rope = 0.0     # |ln(edge width / rope length)| when the two disagree (a sigma term)
    if edges and perc.rope_band_mask is not None:
        # a side where the coarse mask runs on beyond the rope's end with no rope there is a
        # neighbouring trunk merged in: that side's edge is taken at the rope's end
        edges, n_sides = _edges_checked_by_rope(gray, perc, edges)
        if n_sides:
            flags.append("edges_from_rope_band" if n_sides == 2 else "edge_at_rope_end")
    if edges and perc.rope_length_px and perc.rope_band_mask is not None:
        # the rope spans the stem: a stem much wider than the rope band means edges the rope
        # check could not settle (measured on the calibration set: rope length / true stem
        # width 0.90-1.24, 10th-90th percentile); the gap widens the sigma
        ratio = edges.width_px / perc.rope_length_px
        if ratio > ROPE_WIDTH_RATIO_MAX:
            flags.append("width_disagrees_rope")
            width_vs_rope = float(abs(np.log(ratio)))
    if not edges and perc.rope_band_mask is not None:
        # the coarse mask's borders are nowhere near the stem's (e.g. a close stem merged with
        # its neighbour, the mask border tens of pixels off): the rope spans the stem, so its
        # band's ends guide the search instead
        e3 = _edges_two_pass(gray, perc.rope_band_mask, perc)
        if e3 and (not perc.rope_length_px or 0.8 < e3.width_px / perc.rope_length_px < 1.25):
            edges = e3
            flags.append("edges_from_rope_band")
        elif e3.reason == REASON_OUT_OF_PHOTO:
            edges = e3          # the more telling reason
    return edges, flags, width_vs_rope


def channel_mean(rgb: np.ndarray) -> np.ndarray:
    """``rgb.astype(float32).mean(2)`` bit for bit, 7x faster: ``((R + G) + B) / 3`` in float32.

    (numpy's mean over a last axis of 3 is a slow strided reduction: 58 -> 8 ms at 1600 px.)

    Parameters
    ----------
    rgb : (H, W, 3) uint8.

    Returns
    -------
    (H, W) float32.

    Examples
    --------
    >>> px = np.array([[[10, 20, 31]]], np.uint8)
    >>> bool(channel_mean(px)[0, 0] == px.astype(np.float32).mean(2)[0, 0])
    True
    """
    s = rgb[..., 0].astype(np.float32)
    s += rgb[..., 1]
    s += rgb[..., 2]
    s /= 3
    return s


def measure_from_perception(perc: Perception, photo: str = "", *, timings: dict | None = None) -> MeasureResult:
    """Measure the DBH of the roped stem from :class:`Perception`.

    Returns
    -------
    MeasureResult with ``dbh_cm``/``dbh_sigma_cm``/``distance_m``/``scale_source``/``flags``
    and ``estimates_cm``; ``error`` set (and ``dbh_cm`` None) when the stem cannot be measured.
    """
    t0 = time.perf_counter()
    res = MeasureResult(photo=photo, timings_ms=dict(timings or {}))
    cam = perc.camera
    gray = channel_mean(perc.rgb)
    net = perc.source == "network"      # network perception (vs ground truth): wider error model
    SN = {**SIGMA_MODEL_NETWORK, **(perc.sigma_network or {})}
    edges, flags, width_vs_rope = stem_edges(perc, gray)
    if not edges:
        res.error = f"cannot measure the roped stem: {edges.reason}"
        return res
    res.rope_xy = [float(perc.rope_xy[0]), float(perc.rope_xy[1])]
    r_L, r_R = _rays(cam, np.stack([edges.left_xy, edges.right_xy]))
    mid_xy = 0.5 * (edges.left_xy + edges.right_xy)
    # plane through the camera centre and the stem's image mid-line
    p_lo = mid_xy + 50.0 * edges.along
    r_mid, r_lo = _rays(cam, np.stack([mid_xy, p_lo]))
    n_axis_plane = normalize(np.cross(r_mid, r_lo))

    # ---- up direction
    up_sources = {}
    if getattr(cam, "pose", None) is not None:
        R = np.asarray(cam.pose.R_world_from_camera)
        up_sources["pose"] = R.T @ np.array([0, 0, 1.0])
    if perc.use_vanishing and "pose" not in up_sources and not np.any(np.asarray(cam.dist) != 0):
        # the vertical vanishing point of the photo's near-vertical lines (trunk edges):
        # independent of the depth network (measured: median 1.33 deg from the true up)
        from .vanishing import vertical_direction
        t_vp = time.perf_counter()
        vp = vertical_direction(np.clip(gray, 0, 255).astype(np.uint8), np.asarray(cam.K, float))
        res.timings_ms["vanishing"] = 1000 * (time.perf_counter() - t_vp)
        if vp:
            up_sources["vanishing"] = vp.up
            res.debug["vanishing"] = vp
    plane = None
    if perc.depth is None and perc.depth_job is not None:
        t_w = time.perf_counter()
        perc.depth = perc.depth_job.result()
        res.timings_ms["depth"] = res.timings_ms.get("depth", 0.0) + 1000 * (time.perf_counter() - t_w)
    if perc.depth is not None:
        plane, why = _ground_plane(perc, edges, up_sources.get("pose", up_sources.get("vanishing")))
        if plane is not None:
            up_sources["ground_plane"] = plane.n
        else:
            flags.append("no_ground_plane")
    if not up_sources:
        # last resort: the camera assumed level (up = -y); the stem direction below keeps its
        # image lean (up projected into the stem's mid-line plane). (The cross product with the
        # x axis used before was degenerate for a stem in the photo's middle column.)
        up_sources["image"] = np.array([0.0, -1.0, 0.0])
        flags.append("up_from_image")
    up = next(up_sources[k] for k in UP_PRIORITY if k in up_sources)
    if up[1] > 0:
        up = -up
    res.debug["up_sources"] = {k: np.asarray(u_, float) for k, u_ in up_sources.items()}
    res.debug["up_source"] = next(k for k in UP_PRIORITY if k in up_sources)
    # stem direction: up projected into the mid-line plane (keeps the visible lean)
    v = normalize(up - (up @ n_axis_plane) * n_axis_plane)
    if v @ up < 0:
        v = -v

    # ---- axis ray at the rope: bisector of the tangent rays in the cross-section
    a = normalize(project_perpendicular(r_L, v))
    b = normalize(project_perpendicular(r_R, v))
    m = normalize(a + b)
    r_A = normalize(m * np.linalg.norm(project_perpendicular(r_mid, v)) + (r_mid @ v) * v)
    alpha = float(np.arccos(np.clip(a @ b, -1, 1)))
    sin_half = np.sin(alpha / 2)

    # ---- scale candidates: (axis distance along r_A in metres, relative sigma)
    cands: dict[str, tuple[float, float]] = {}
    # stem base in the image: where the user tapped, else traced down the stem mask
    if perc.base_xy is not None:
        base_xy, base_status = np.asarray(perc.base_xy, np.float64), "user"
        flags.append("stem_base_from_user")
    else:
        base_xy = None
        # no segmented stem to confirm where the tracked edges end (the mask is the rope's band),
        # or edges that are not the stem's: the edge tracker does not look for the base
        unconfirmed = bool(perc.extra.get("tree_mask_from_rope") or "width_disagrees_rope" in flags)
        if perc.base_finder is not None and (BASE_NETWORK_UNCONFIRMED or not unconfirmed):
            # the stem-base network reads the strip below the rope (models.runtime_base)
            t_b = time.perf_counter()
            est = perc.base_finder(perc.rgb, mid_xy, _stem_image_direction(cam, mid_xy, edges.along, up_sources),
                                   edges.width_px)
            res.timings_ms["base"] = 1000 * (time.perf_counter() - t_b)
            res.debug["base_network"] = est
            if est:
                base_xy, base_status = np.asarray(est.xy, np.float64), "network"
                flags.append("stem_base_from_network")
                if est.p_base < BASE_P_STRONG:
                    base_status = "network_weak"
        if base_xy is None and unconfirmed:
            base_status = "unconfirmed"
        elif base_xy is None:
            base_xy, base_status, _trk = track_stem_base(gray, edges, perc.ground_mask, perc.tree_mask, rgb=perc.rgb,
                                                         rope_half_px=perc.rope_half_px)
            res.debug["base_tracked"] = (base_xy, base_status, _trk)
            if BASE_FINDER == "mask" or (BASE_FINDER == "either" and base_xy is None):
                base_xy, base_status = trace_stem_base(perc.tree_mask, perc.ground_mask, mid_xy, edges.along,
                                                       edges.width_px)
                res.debug["base_traced"] = (base_xy, base_status)

    def base_metrology(xy):
        """(axis distance along r_A, depth of the base) with ``xy`` the stem's front ground contact."""
        r_B = _rays(cam, np.asarray(xy, np.float64)[None])[0]
        lt, lb, _ = metrology_distance(r_A, r_B, v, ROPE_HEIGHT_M)
        if lt > 0 and lb > 0:
            # the visible base is the front contact point; the axis is ~rho further away
            B_axis = lb * r_B + lt * sin_half * normalize(project_perpendicular(r_B, v))
            lt, lb, _ = metrology_distance(r_A, normalize(B_axis), v, ROPE_HEIGHT_M)
        return lt, lb

    if base_xy is not None:
        lt, lb = base_metrology(base_xy)
        if lt > 0 and lb > 0:
            src = "pose" if "pose" in up_sources else "stem_base"
            if base_status == "user" and src == "stem_base":
                src = "stem_base_user"
            elif base_status == "network_weak" and src == "stem_base":
                src = "stem_base_weak"
            if lt > 0:
                table = SN if net else SIGMA_MODEL
                cands[src] = (lt, table.get(src, SN[src]))
        if base_status == "user" and not (lt > 0 and lb > 0):
            flags.append("stem_base_user_rejected")      # the tapped point is not below the rope
    else:
        flags.append(f"stem_base_{base_status}")
        trk = res.debug.get("base_tracked")
        if trk is not None and trk[2].get("end_xy") is not None:
            # the lowest point the stem was followed to: the base is there or below it
            lt, lb = base_metrology(trk[2]["end_xy"])
            if lt > 0 and lb > 0:
                res.debug["scale_bound"] = (float(lt), base_status)
    if perc.rope_diameter_m:
        # the rope as a ruler: a tube of known diameter D subtends D / rho radians at distance
        # rho, seen across its band at the stem's front
        T_read = float(perc.rope_thickness_px or 0.0)
        T = T_read / ROPE_RULER_FWHM_RATIO       # the tube's thickness (the half-maximum width reads narrow)
        # blur widens thin ropes: the gate is on the pixels it was measured in (the full-resolution
        # photo's where it was read there)
        T_native = float(perc.rope_thickness_native_px or T_read)
        if T_native < ROPE_RULER_MIN_PX:
            flags.append("rope_too_thin_for_scale")
        elif not (perc.rope_contrast or 0.0) >= ROPE_RULER_MIN_CONTRAST:
            flags.append("rope_too_faint_for_scale")
        else:
            n_band = np.array([-perc.rope_dir[1], perc.rope_dir[0]], np.float64)
            n_band /= np.linalg.norm(n_band) + 1e-12
            p0 = np.asarray(perc.rope_xy, np.float64)
            r1, r2 = _rays(cam, np.stack([p0 - 0.5 * T * n_band, p0 + 0.5 * T * n_band]))
            ang = float(np.arccos(np.clip(r1 @ r2, -1, 1)))
            if ang > 0:
                rho = float(perc.rope_diameter_m) / ang       # camera -> the rope at the stem's front
                lt = (rho + 0.5 * float(perc.rope_diameter_m)) / max(1 - sin_half, 1e-6)
                cands["rope_diameter"] = (lt, SN["rope_diameter"])
    if "pose" in up_sources and "pose" not in cands:
        # ground plane from the calibrated pose: axis base on the plane z = 0
        h = float(cam.pose.height_m)
        nv = float(up @ v)
        den = float(up @ r_A)
        if abs(den) > 1e-3:
            lt = (ROPE_HEIGHT_M * nv - h) / den
            cond = abs(ROPE_HEIGHT_M - h) / max(lt, 1e-6)
            if lt > 0:
                cands["pose"] = (lt, SIGMA_MODEL["pose"] + 0.01 / max(cond, 1e-3))
    z_front = np.nan
    if perc.depth is not None:
        # depth of the axis at the rope from the depth map: front surface + radius
        off = 3 * perc.rope_half_px * edges.along
        if not perc.depth_is_metric and STEM_DEPTH_READ == "nearest":
            z_front = _depth_nearest_across(perc.depth, edges.left_xy + off, edges.right_xy + off)
        else:
            line = np.array([edges.left_xy + f * (edges.right_xy - edges.left_xy) for f in (0.35, 0.5, 0.65)])
            zs = [_depth_at(perc.depth, perc.tree_mask, p + off, 2) for p in line]
            if not np.isfinite(zs).any() and perc.edge_mask is not None:
                # the coarse tree mask misses the stem at the rope: the stem between its edges
                zs = [_depth_at(perc.depth, perc.edge_mask, p + off, 2) for p in line]
            z_front = float(np.nanmedian(zs)) if np.isfinite(zs).any() else np.nan
        if np.isfinite(z_front):
            lam_front = z_front / max(r_A[2], 1e-6)
            lam_axis = lam_front / max(1 - sin_half, 1e-6)      # axis = front surface + radius
            if plane is not None:
                PA = lam_axis * r_A
                hA = float(plane.height(PA[None])[0])
                nv = float(plane.n @ v)
                gp_key = "ground_plane" if perc.depth_is_metric else "ground_plane_network"
                if hA > 1e-6 and nv > 0.5:
                    s = ROPE_HEIGHT_M * nv / hA
                    # conditioning: relative height of the rope vs plane fit noise
                    sig = (SN if net else SIGMA_MODEL)[gp_key] + plane.rms_m / max(hA, 1e-6)
                    cands["ground_plane"] = (s * lam_axis, sig)
                # (the camera's height along the vanishing-point up was measured worse: median
                # |ln error| 0.318 vs 0.257 from the plane's offset, calibration set seed 9100)
                h_cam = float(plane.c)
                if "pose" not in up_sources and not perc.depth_is_metric and h_cam > 1e-6:
                    # handheld prior: the phone is held 1.1-1.9 m above the ground
                    sig = np.hypot(SN["camera_height"], plane.rms_m / h_cam)
                    cands["camera_height"] = (CAMERA_HEIGHT_PRIOR_M / h_cam * lam_axis, float(sig))
            if perc.depth_is_metric:
                cands["depth_gt"] = (lam_axis, 0.005)
            else:
                cands["network"] = (lam_axis, SN["network"])
    if not cands:
        res.error = "cannot set the metric scale: no stem base, ground plane, pose or depth"
        return res
    res.debug["scale_candidates"] = {k: (float(l), float(sg)) for k, (l, sg) in cands.items()}
    res.debug["stem_width_px"] = float(edges.width_px)
    res.debug["fx_px"] = float(np.asarray(cam.K, float)[0, 0])
    order = ["depth_gt", "pose", "stem_base_user", "ground_plane", "stem_base", "stem_base_weak", "rope_diameter",
             "camera_height",
             "network"]
    # inverse-variance combination of the geometric sources that agree
    # the leading source: least typical error where measured (manifest "rank"), else least sigma
    rank = (perc.rank_network or {}) if net else {}
    best = min(cands, key=lambda k: rank.get(_SN_KEY.get(k, k), cands[k][1]))
    lam, sig_rel = cands[best]
    used = [best]
    for k, (l2, s2) in cands.items():
        if k == best or k == "network":
            continue
        if abs(l2 / lam - 1) < 2.5 * np.hypot(s2, sig_rel):
            w1, w2 = 1 / sig_rel ** 2, 1 / s2 ** 2
            lam = (w1 * lam + w2 * l2) / (w1 + w2)
            sig_rel = 1 / np.sqrt(w1 + w2)
            used.append(k)
        else:
            flags.append(f"scale_disagree_{k}")
    if net and len(used) > 1:
        # the sources share one depth map and masks: their errors are correlated, so agreeing
        # does not shrink the uncertainty below the best single source's
        sig_rel = min(cands[k][1] for k in used)
    # the leading source first, then the others that agreed with it
    res.scale_source = "+".join([best] + sorted((k for k in used if k != best), key=order.index))
    res.debug["scale_leader"], res.debug["lam_combined"] = best, float(lam)
    calib = perc.distance_calibration if net else None
    if calib and best in NETWORK_SCALE_SOURCES:
        # the network's distances are noisier than the spread of distances people stand at:
        # E[ln true | ln network] measured on the calibration sets shrinks them towards the
        # typical distance (error model, Theil-Sen fit; see README "How the scale is set")
        res.debug["lam_uncalibrated"] = float(lam)
        lam = float(np.exp(calib["a"] + calib["b"] * np.log(lam)))
        flags.append("distance_calibrated")
        if calib.get("sigma"):
            # the measured spread of the calibrated distances (narrower than the raw network's)
            sig_rel = float(calib["sigma"])
    bound = res.debug.get("scale_bound")
    res.debug["lam_before_bound"] = float(lam)
    if (net and bound is not None and bound[1] in SCALE_BOUND_STATUSES and best not in PRECISE_SCALE_SOURCES
            and lam > bound[0] * (1 + SCALE_BOUND_SLACK)):
        # the stem was followed down to where something hides it: its base is there or lower,
        # so the rope-to-base metrology through that point is the farthest the stem can be.
        # (calibration sets, 160 photos: the bound was never more than 4.3 % below the true
        # distance in 25 photos; it capped 4 network scales, all nearer the truth after)
        lam = bound[0]
        flags.append("scale_capped_by_visible_stem")
        res.scale_source = "visible_stem+" + res.scale_source
    if best == "network":
        flags.append("scale_from_network")
    A = lam * r_A
    D_axis = float(np.linalg.norm(project_perpendicular(A, v)))
    res.distance_m = float(np.linalg.norm(A[[0, 2]]))   # horizontal-ish distance camera -> stem axis

    # ---- DBH estimators
    est, sig = {}, {}
    d_tan = tangent_diameter(r_L, r_R, v, A)
    est["tangent"] = d_tan
    edge_rel = np.hypot(SIGMA_MODEL["edge_px"], edges.edge_rms_px) * np.sqrt(2) / max(edges.width_px, 1.0)
    sig["tangent"] = np.sqrt(SIGMA_MODEL["ovality"] ** 2 + edge_rel ** 2
                             + (SN["width"] ** 2 if net else 0.0))
    cloud_fit = None
    if perc.z1 is not None or perc.silhouette_fn is not None:
        cloud_fit, slice_uv = _cloud_circle(perc, edges, A, v, lam, r_A)
        if cloud_fit:
            est["cloud"] = 2 * cloud_fit.r
            arc_pen = 0.02 * max(0.0, (300 - cloud_fit.arc_deg) / 120)
            sig["cloud"] = np.sqrt(SIGMA_MODEL["ovality"] ** 2 * 0.5 + SIGMA_MODEL["cloud_extra"] ** 2 + arc_pen ** 2
                                   + edge_rel ** 2 + (SN["cloud"] ** 2 if net else 0.0))
            res.debug["slice_uv"] = slice_uv
            res.debug["circle"] = (cloud_fit.xc, cloud_fit.yc, cloud_fit.r)
            if cloud_fit.arc_deg < 180:
                flags.append("short_arc")
            if cloud_fit.inlier_ratio < 0.7:
                flags.append("low_inlier_ratio")
    if net and "cloud" in est and best in PRECISE_SCALE_SOURCES:
        # with a precise scale, the tree network's circle only checks the tangent estimate:
        # averaging it in made DBH worse (calibration set, stem base tapped on 20 photos: MAE
        # 1.90 cm tangent only vs 2.63 cm combined; the circle alone 6.5 cm)
        flags.append("circle_as_check")
        if abs(np.log(est["cloud"] / est["tangent"])) > 2.5 * np.hypot(sig["tangent"], sig["cloud"]):
            flags.append("estimators_disagree")
        est_all = dict(est)
        est = {"tangent": est["tangent"]}
    else:
        est_all = est
    ws = {k: 1 / sig[k] ** 2 for k in est}
    d = sum(ws[k] * est[k] for k in est) / sum(ws.values())
    rel_sig_est = 1 / np.sqrt(sum(ws.values()))
    if len(est) > 1:
        spread = abs(est["tangent"] - est["cloud"]) / d
        if spread > 2.5 * np.hypot(sig["tangent"], sig["cloud"]):
            flags.append("estimators_disagree")
        rel_sig_est = max(rel_sig_est, spread / 2)
    # edges that disagree with the rope band's length are shared by both estimators (the slice
    # lies between them): the gap widens the uncertainty of the combination
    rel_sig_est = float(np.hypot(rel_sig_est, width_vs_rope))
    rel_sig = np.hypot(rel_sig_est, sig_rel)
    res.dbh_cm = 100 * d
    res.dbh_sigma_cm = 100 * d * rel_sig
    res.estimates_cm = {k: 100 * v_ for k, v_ in est_all.items()}
    if edges.width_px < 12:
        flags.append("few_pixels_across_stem")
    res.flags = flags
    res.debug.update(dict(edges=edges, edges_xy=np.stack([edges.left_xy, edges.right_xy]), axis_dir=v,
                          axis_point=A, scale_candidates=cands, D_axis=D_axis, base_xy=base_xy,
                          rope_xy=np.asarray(perc.rope_xy)))
    res.timings_ms["geometry"] = 1000 * (time.perf_counter() - t0)
    return res


def _cloud_circle(perc: Perception, edges, A, v, lam, r_A):
    """Front/back points of the stem slice at the rope -> circle in the cross-section plane."""
    cam = perc.camera
    if perc.silhouette_fn is not None:
        z1, z2 = perc.silhouette_fn(float(A[2]), edges)
        scale = 1.0
    else:
        z1, z2 = perc.z1, perc.z2            # metric (ground truth)
        scale = 1.0
    if z1 is None:
        from .geometry import CircleFit
        return CircleFit(reason="no silhouette"), None
    pts = []
    u = edges.across
    w = edges.width_px
    for t in (-3, -2, 2, 3):
        base = 0.5 * (edges.left_xy + edges.right_xy) + t * max(1.0, 1.5 * perc.rope_half_px) * edges.along
        for f in np.linspace(-0.5, 0.5, max(9, int(w))):
            p = base + f * w * u
            x, y = int(round(p[0])), int(round(p[1]))
            if not (0 <= y < z1.shape[0] and 0 <= x < z1.shape[1]):
                continue
            if not perc.tree_mask[y, x] or z1[y, x] <= 0:
                continue
            pts.append((p[0], p[1], z1[y, x] * scale, z2[y, x] * scale))
    if len(pts) < 6:
        from .geometry import CircleFit
        return CircleFit(reason="too few slice points"), None
    P = np.array(pts)
    nxy = cam.undistort_points(P[:, :2], normalized=True)
    front = np.c_[nxy * P[:, 2:3], P[:, 2]]
    back = np.c_[nxy * P[:, 3:4], P[:, 3]]
    X = np.concatenate([front, back[P[:, 3] > P[:, 2] + 1e-4]])
    e1 = normalize(project_perpendicular(A, v))
    e2 = np.cross(v, e1)
    uv = np.c_[X @ e2, X @ e1]
    rmax = 2.0 * np.linalg.norm(A) * np.sin(0.5 * np.arccos(np.clip(
        normalize(project_perpendicular(_rays(cam, edges.left_xy[None])[0], v)) @
        normalize(project_perpendicular(_rays(cam, edges.right_xy[None])[0], v)), -1, 1))) + 0.05
    thr = max(0.003, 0.03 * rmax)
    return fit_circle(uv, threshold=thr, r_max=rmax), uv
