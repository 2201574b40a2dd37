"""The measuring path's geometry: from :class:`Perception` to a metric DBH (:func:`measure_from_perception`).

Imported by the measuring pipeline (:mod:`monodbh.toolkit.pipeline`), ground-truth perception
(:mod:`monodbh.toolkit.evaluation.ground_truth`) and evaluation; imports numpy, cv2, the rope package's red-ness map
and :mod:`monodbh.toolkit.result` (scipy and scikit-image inside the circle fit). One module per
stage: :mod:`.perception` (the input), :mod:`.config` (every tuning parameter,
:class:`GeometryConfig`), :mod:`.fits` (rays, planes, metrology, circle), :mod:`.edges` (trunk
edges at the rope), :mod:`.stem_edges` (the edge pair checked against the rope band),
:mod:`.stem_track` (the edge tracker), :mod:`.stem_base` (base states, visible-stem bound),
:mod:`.vanishing` (the vertical vanishing point), :mod:`.up` (up and the stem's direction),
:mod:`.ground` (the ground plane), :mod:`.depth_read` (the depth at the stem), :mod:`.sigma`
(the sigma tables), :mod:`.scale` (scale candidates and their combination), :mod:`.dbh`
(the estimators), :mod:`.measure` (the stages in order).
"""
from .config import (ROPE_HEIGHT_M, DbhConfig, EdgeConfig, GeometryConfig, RopeRulerConfig, ScaleConfig,
                     SigmaConfig, StemBaseConfig, StemEdgesConfig, UpConfig, VanishingConfig)
from .edges import REASON_OUT_OF_PHOTO, TrunkEdges, channel_mean, combine_edges, rope_row_contrast, trunk_edges
from .fits import (CircleFit, PlaneFit, fit_circle, fit_plane_ransac, metrology_distance, normalize, pixel_rays,
                   project_perpendicular, rays_from_normalized, tangent_diameter)
from .measure import measure_from_perception
from .perception import Perception
from .scale import NETWORK_SCALE_SOURCES
from .stem_edges import stem_edges
from .stem_track import track_stem_base
from .vanishing import VerticalEstimate, line_segments, vertical_direction

__all__ = [
    "Perception", "measure_from_perception",
    "GeometryConfig", "EdgeConfig", "StemEdgesConfig", "StemBaseConfig", "VanishingConfig", "UpConfig",
    "ScaleConfig", "RopeRulerConfig", "SigmaConfig", "DbhConfig", "ROPE_HEIGHT_M", "NETWORK_SCALE_SOURCES",
    "TrunkEdges", "trunk_edges", "stem_edges", "track_stem_base", "rope_row_contrast", "combine_edges",
    "channel_mean", "REASON_OUT_OF_PHOTO",
    "CircleFit", "PlaneFit", "fit_circle", "fit_plane_ransac", "metrology_distance", "normalize", "pixel_rays",
    "project_perpendicular", "rays_from_normalized", "tangent_diameter",
    "VerticalEstimate", "vertical_direction", "line_segments",
]
