"""The geometry's tuning parameters: :class:`GeometryConfig`, one frozen dataclass per stage.

Imported by every module of :mod:`monodbh.toolkit.geometry` (it imports nothing of the package).
Each stage takes its part of the configuration (``config: XConfig | None = None``, the defaults
when None); :func:`~.measure.measure_from_perception` takes the whole :class:`GeometryConfig`.
Each field says in one line what it means; the measurements that set it are in the decision
record it links (``docs/decisions/<name>.md``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["ROPE_HEIGHT_M", "GeometryConfig", "EdgeConfig", "StemEdgesConfig", "StemBaseConfig",
           "VanishingConfig", "UpConfig", "ScaleConfig", "RopeRulerConfig", "SigmaConfig", "DbhConfig"]

#: height of the rope above the stem's base (m): the measuring protocol (the rope is tied at
#: breast height, 1.3 m), not a tuning parameter
ROPE_HEIGHT_M = 1.3


@dataclass(frozen=True)
class EdgeConfig:
    """The search for the stem's silhouette edges at the rope (:func:`~.edges.trunk_edges`)."""

    #: sampling lines across the stem, half above and half below the rope band
    n_lines: int = 16


@dataclass(frozen=True)
class StemEdgesConfig:
    """The edge pair checked against the rope band (:func:`~.stem_edges.stem_edges`);
    decision record ``docs/decisions/stem-edges-rope-check.md``."""

    #: a side's mask edge beyond the rope's end by more than this many pixels (or
    #: ``rope_gap_min_fraction``) may be a merged neighbour (stem-edges-rope-check.md)
    rope_gap_min_px: float = 3.0
    #: ... or by more than this fraction of the rope band's edge width (stem-edges-rope-check.md)
    rope_gap_min_fraction: float = 0.04
    #: ... and is replaced where the rope's row there is less red than this fraction of the rope's
    #: own contrast (stem-edges-rope-check.md)
    rope_gap_max_ratio: float = 0.2
    #: the check applies only where the rope's red-ness contrast across the stem is above this
    #: (stem-edges-rope-check.md)
    rope_gap_min_contrast: float = 0.02
    #: how far (fraction of the stem's width, plus 1 px) the rope may stray from its centre line's
    #: quadratic (on along the end's tangent past the line's ends) where its row is read
    #: (stem-edges-rope-check.md)
    rope_curve_tolerance: float = 0.02
    #: without a centre line (``Perception.rope_polyline`` None), a straight row along the rope's
    #: direction is read, which may sag this fraction of the stem's width (stem-edges-rope-check.md)
    rope_straight_sag: float = 0.05
    #: a side moves out to the rope's end where the rope's row stays at least this fraction as
    #: red as across the stem (stem-edges-rope-check.md) ...
    rope_extend_level: float = 0.5
    #: ... more than this fraction of the stem's width past the edge (read up to
    #: ``rope_extend_max`` of it, across gaps of ``rope_extend_gap`` of it) ...
    rope_extend_min: float = 0.12
    rope_extend_max: float = 0.5
    rope_extend_gap: float = 0.03
    #: ... and the edge found there is at least this many times as strong (median gradient) as
    #: the one it replaces (stem-edges-rope-check.md)
    rope_extend_min_strength: float = 1.0
    #: where the rope band runs on beyond a side's mask edge (by the same margin) and its row
    #: there is at least this fraction as red as across the stem, the mask edge lies inside the
    #: stem and that side's edge is taken at the rope's end (stem-edges-rope-check.md)
    rope_overrun_min_ratio: float = 0.5
    #: ... when the band runs on past the mask edge by more than the rope's half thickness plus
    #: this many pixels (and the ``rope_gap_min_*`` margin) (stem-edges-rope-check.md)
    rope_overrun_extra_px: float = 1.5
    #: an edge point whose inner side (up to ``rope_end_reach`` rope half-thicknesses inward)
    #: is redder than the stem's bark on its line by at least this fraction of the rope's own
    #: contrast lies on the rope's knot or hanging ends, not on the stem's silhouette: it is
    #: left out of that side's line (0: off) (stem-edges-rope-check.md)
    rope_end_red_ratio: float = 0.5
    rope_end_reach: float = 2.0
    #: ... where those points lie outward of the side's other points (along the stem's direction)
    #: by more than this many rope half-thicknesses (and 1 px) (stem-edges-rope-check.md)
    rope_end_min_out: float = 0.5
    #: edges wider than this factor times the rope band's length are flagged
    #: ``width_disagrees_rope`` and the gap enters the DBH sigma (stem-edges-rope-check.md)
    width_rope_ratio_max: float = 1.3
    #: edges narrower than this factor times the rope band's length (the band spans the stem;
    #: its knot and round ends overshoot it by little) are flagged the same way
    #: (stem-edges-rope-check.md)
    width_rope_ratio_min: float = 0.5
    #: edges found at the rope band's ends replace missing mask edges when their width over the
    #: rope length lies strictly in this range (stem-edges-rope-check.md)
    band_width_ratio: tuple[float, float] = (0.8, 1.25)
    #: the second pass (sampled across the stem as first found) is kept unless its width differs
    #: from the first by this fraction or more
    second_pass_max_change: float = 0.5
    #: the stem-edge network moves a side where its edge and the gradient's are more than this many
    #: pixels apart ... (stem-edge-network.md)
    edge_net_tol_px: float = 1.0
    #: ... and this fraction of the stem's width ...
    edge_net_tol_frac: float = 0.015
    #: ... and the network's probability mass around its edge is at least this
    edge_net_min_mass: float = 0.85


@dataclass(frozen=True)
class StemBaseConfig:
    """Where the stem meets the ground: the stem-base network's outcome and the edge tracker
    (:mod:`~.stem_base`, :func:`~.stem_track.track_stem_base`); decision record
    ``docs/decisions/stem-base.md``."""

    #: a stem-base network base with a probability under this is the scale source
    #: ``stem_base_weak`` (its own sigma) (stem-base.md)
    p_strong: float = 0.9
    #: a tracked edge point counts when its gradient is at least this fraction of that side's
    #: gradient near the rope (stem-base.md)
    min_rel_gradient: float = 0.35
    #: ... or at least this many times the typical gradient along its search line (stem-base.md)
    min_snr: float = 3.0
    #: the tracking stops after a gap (both sides lost) of this fraction of the stem width
    #: (stem-base.md)
    max_miss_frac: float = 0.4
    #: the tracking stops where the stem's interior colour departs from its colour below the rope
    #: by more than this many standard deviations (grass or litter in front) (stem-base.md)
    max_colour_z: float = 4.0
    #: where the edge tracker ends on what looks like the ground, that end sets the scale as a
    #: base (``stem_base``); off: it only bounds the distance from above (base status
    #: "tracked", flag ``stem_base_tracked``), as an occluded end does (stem-base.md)
    tracked_base_sets_scale: bool = False
    #: where the segmented stem runs on below the network's base by more than this fraction of
    #: the rope-to-base span, that base is a bush or a fallen branch in front of the stem, not
    #: its foot: the lowest segmented point only bounds the distance (base status "occluded",
    #: flag ``stem_base_above_visible_stem``) (stem-base.md)
    mask_overrun_max: float = 0.25
    #: the network's strip cut again as the stem's edges could also have been found: (width
    #: factor, shift across in stem widths, rotation in degrees) each; empty: no check (stem-base.md)
    ambiguity_strips: tuple[tuple[float, float, float], ...] = (
        (0.85, 0.0, 0.0), (1.2, 0.0, 0.0), (1.0, -0.15, 0.0), (1.0, 0.15, 0.0), (1.0, 0.0, -2.0), (1.0, 0.0, 2.0))
    #: where one of those strips puts the base lower by more than this fraction of the
    #: rope-to-base span, both bases are kept: the scale is their distances' geometric mean as a
    #: weak base, its sigma widened by half their log ratio (base status "network_ambiguous",
    #: flag ``stem_base_ambiguous``) (stem-base.md)
    ambiguity_max_lower: float = 0.25
    #: the strips are cut again only for a base the network gives less than this probability
    #: (a time saving: no surer base moved that far) (stem-base.md)
    ambiguity_p_max: float = 0.95


@dataclass(frozen=True)
class VanishingConfig:
    """The vertical vanishing point of near-vertical lines (:func:`~.vanishing.vertical_direction`);
    decision record ``docs/decisions/stem-direction.md``."""

    #: shortest line segment kept, as a fraction of the image height
    min_len_frac: float = 0.06
    #: largest angle of a kept segment from the image's vertical axis (degrees)
    max_tilt_deg: float = 30.0
    #: angle between a segment's interpretation plane and the direction counted as agreeing in the
    #: RANSAC search (degrees)
    inlier_deg: float = 1.5
    #: scale of the refinement's Cauchy weights (degrees): larger averages more stems
    refine_deg: float = 4.0
    #: RANSAC hypotheses (segment pairs)
    iters: int = 400
    #: seed of the RANSAC sampling
    seed: int = 0
    #: fewest distinct stems (segment columns) accepted
    min_groups: int = 3
    #: hypotheses farther than this from the level camera's up are dropped (degrees; pitch and
    #: roll beyond any handheld photo)
    max_from_level_deg: float = 40.0
    #: width of the image columns that group segments into stems (fraction of the image width)
    column_frac: float = 0.02
    #: the direction's 1-sigma is this over the square root of the stem count (degrees), at least
    #: the lines' own scatter (stem-direction.md)
    sigma_columns_deg: float = 11.0
    #: iterations of the Cauchy-weighted least-squares refinement
    refine_steps: int = 8
    #: the line detector's largest distance of an edge pixel from its line (pixels)
    line_distance_px: float = 1.414
    #: the line detector's Canny thresholds (low, high) on the grey image
    canny_thresholds: tuple[int, int] = (30, 60)


@dataclass(frozen=True)
class UpConfig:
    """The up direction and the stem's direction (:mod:`~.up`); decision record
    ``docs/decisions/stem-direction.md``."""

    #: which up direction is used, best first: the calibrated pose, the vertical vanishing point,
    #: the depth map's ground plane, the image's vertical (stem-direction.md)
    priority: tuple[str, ...] = ("pose", "vanishing", "ground_plane", "image")
    #: weight of the stem edges' own image direction against the image of the vertical (pose or
    #: vanishing point) in the direction down the stem (stem-direction.md)
    stem_direction_edge_weight: float = 0.3


@dataclass(frozen=True)
class ScaleConfig:
    """The combination of the scale candidates (:mod:`~.scale`); decision records
    ``docs/decisions/scale-combination.md`` and ``docs/decisions/visible-stem-bound.md``."""

    #: scale sources precise enough (a few per cent) that, with network perception, the tangent
    #: estimate alone sets the DBH and no visible-stem cap applies (scale-combination.md)
    precise_sources: tuple[str, ...] = ("pose", "stem_base_user", "stem_base", "stem_base_weak")
    #: a candidate agrees with the leading source when their ratio is within this many combined
    #: sigmas of 1 (then averaged in), else it is flagged ``scale_disagree_<source>``
    #: (scale-combination.md)
    agree_sigmas: float = 2.5
    #: sources whose typical errors (the error model's ``rank``) are within this fraction of the
    #: least one count as tied (about the sampling error of a median over ~300 calibration
    #: photos); the tie goes to the candidate with the least sigma, the lighter tail
    #: (scale-combination.md)
    rank_tie: float = 0.05
    #: typical height of a handheld phone above the ground (m): the scale prior ``camera_height``
    #: (scale-combination.md)
    camera_height_prior_m: float = 1.5
    #: relative 1-sigma of the ground-truth depth map's distance (the source ``depth_gt``)
    depth_gt_sigma: float = 0.005
    #: the edge tracker's outcomes whose lowest tracked point bounds the distance from above
    #: (visible-stem-bound.md)
    bound_statuses: tuple[str, ...] = ("occluded", "tracked")
    #: a scale more than this fraction beyond the visible stem's bound is capped to the bound
    #: (visible-stem-bound.md)
    bound_slack: float = 0.03
    #: ... unless the leading scale's relative 1-sigma is under this (a marker read edge to edge):
    #: the bound is then flagged ``scale_disagree_visible_stem`` instead (visible-stem-bound.md)
    bound_min_sigma: float = 0.1


@dataclass(frozen=True)
class RopeRulerConfig:
    """The rope of known diameter as a ruler (``--rope-mm``, :func:`~.scale.candidate_rope_diameter`);
    decision record ``docs/decisions/rope-ruler.md``."""

    #: the rope's thickness is trusted from this many pixels on, in the pixels it was measured in
    #: (rope-ruler.md)
    min_px: float = 5.0
    #: ... where its mean profile's red-ness contrast is at least this (rope-ruler.md)
    min_contrast: float = 0.09
    #: the red-ness profile's full width at half maximum over the tube's true thickness
    #: (rope-ruler.md)
    fwhm_ratio: float = 0.944
    #: the marker's distance has the relative 1-sigma ``hypot(floor, px / T)`` for a thickness of
    #: ``T`` pixels (those it was read in): read edge to edge ``(floor, px)`` =
    #: ``edge_sigma``, else (half-maximum width) ``fwhm_sigma`` (rope-ruler.md)
    edge_sigma: tuple[float, float] = (0.025, 0.45)
    #: ... the half-maximum width's ``(floor, px)`` (it reads a blur-dependent fraction of the tube)
    fwhm_sigma: tuple[float, float] = (0.08, 0.8)


def _sigma_model() -> dict[str, float]:
    return dict(ovality=0.030, edge_px=0.35, pose=0.02, ground_plane=0.035, stem_base=0.04,
                network=0.15, cloud_extra=0.05, ground_plane_network=0.30, camera_height=0.20)


def _sigma_model_network() -> dict[str, float]:
    return dict(network=0.37, ground_plane_network=0.47, camera_height=0.46, stem_base=0.50, stem_base_weak=0.50,
                pose=0.05, width=0.14, cloud=0.28, stem_base_user=0.06, rope_diameter=0.12)


@dataclass(frozen=True)
class SigmaConfig:
    """The default relative 1-sigma tables of the scale sources and DBH estimators (the shipped
    networks' measured error model, ``Perception.sigma_network``, overrides ``model_network``);
    decision record ``docs/decisions/scale-combination.md``."""

    #: relative 1-sigma terms (fractions) with exact perception; ``ovality`` (the single-view
    #: floor), ``edge_px`` (pixels) and ``cloud_extra`` apply to any perception (scale-combination.md)
    model: dict[str, float] = field(default_factory=_sigma_model)
    #: relative 1-sigma terms with network perception (coarse masks, network depth), by source or
    #: estimator (``width``: the tangent estimate, ``cloud``: the tree network's circle)
    #: (scale-combination.md)
    model_network: dict[str, float] = field(default_factory=_sigma_model_network)


@dataclass(frozen=True)
class DbhConfig:
    """The DBH estimators and their combination (:mod:`~.dbh`); decision record
    ``docs/decisions/scale-combination.md`` (circle as check)."""

    #: the tangent estimate and the circle disagree (``estimators_disagree``) beyond this many
    #: combined sigmas
    disagree_sigmas: float = 2.5
    #: a circle whose inliers cover less than this arc is flagged ``short_arc`` (degrees)
    short_arc_deg: float = 180.0
    #: a circle with fewer inliers than this fraction is flagged ``low_inlier_ratio``
    min_inlier_ratio: float = 0.7
    #: a stem narrower than this many pixels is flagged ``few_pixels_across_stem``
    few_pixels_px: float = 12.0
    #: with network perception the tree network's circle only checks the tangent estimate
    #: whatever the scale source; False averages it in where no precise source leads
    #: (``ScaleConfig.precise_sources``; scale-combination.md)
    circle_check_only: bool = True


@dataclass(frozen=True)
class GeometryConfig:
    """Every tuning parameter of the geometry, by stage (see each stage's class)."""

    #: trunk edges at the rope
    edges: EdgeConfig = field(default_factory=EdgeConfig)
    #: the edge pair checked against the rope band
    stem_edges: StemEdgesConfig = field(default_factory=StemEdgesConfig)
    #: the stem base: network outcome and edge tracker
    stem_base: StemBaseConfig = field(default_factory=StemBaseConfig)
    #: the vertical vanishing point
    vanishing: VanishingConfig = field(default_factory=VanishingConfig)
    #: the up direction and the stem direction
    up: UpConfig = field(default_factory=UpConfig)
    #: the scale candidates' combination and the visible-stem bound
    scale: ScaleConfig = field(default_factory=ScaleConfig)
    #: the rope as a ruler
    rope_ruler: RopeRulerConfig = field(default_factory=RopeRulerConfig)
    #: the default sigma tables
    sigma: SigmaConfig = field(default_factory=SigmaConfig)
    #: the DBH estimators
    dbh: DbhConfig = field(default_factory=DbhConfig)
