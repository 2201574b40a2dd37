"""Configuration of the measuring path: :class:`MeasureConfig`, the documented parameters a
:class:`~monodbh.toolkit.pipeline.Session` measures with.

Lives here: the top-level parameters and the composition of each stage's own configuration.
Imported by the library's modules; imports only their config classes.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field

from .geometry.config import GeometryConfig
from .rope.config import RopeConfig

__all__ = ["MeasureConfig"]


@dataclass(frozen=True)
class MeasureConfig:
    """Parameters of ``dbh measure`` (defaults: the shipped behaviour).

    Attributes
    ----------
    work_long_side_px : photos are measured at this long side (pixels; never upscaled); edges are
        located to sub-pixel precision there (docs/decisions/work-resolution.md).
    rope_full_resolution : with a known rope diameter, read the rope's thickness again on the
        full-resolution photo when it is larger than the working image
        (docs/decisions/work-resolution.md).
    marker_edges : with a known marker width, read the marker's thickness edge to edge (its
        silhouette, :func:`~monodbh.toolkit.rope.marker_edges.marker_thickness`) instead of the
        red-ness profile's half-maximum width (docs/decisions/rope-ruler.md).
    overlap_networks : run the segmenter and the depth network on a background thread while the
        band detector searches the rope (docs/decisions/threads.md); off: they run when first needed.
    depth_mirror_average : the depth network sees the photo and its mirror image and averages them
        (docs/decisions/threads.md); the error model is valid only for the setting it was measured with.
    stem_base_threshold : the stem-base network's probability needed to use its base
        (docs/decisions/stem-base.md).
    edge_network : the stem-edge network (where shipped) checks the stem's edges at the rope
        (docs/decisions/stem-edge-network.md).
    ort_spin : onnxruntime's idle threads spin between work items instead of sleeping (faster
        alone on a machine, slower beside the rope search on 2 cores; docs/decisions/threads.md).
        Default: the environment variable ``MONODBH_ORT_SPIN=1``, else off.
    sideways_score_max : a photo whose light comes from a side by more than this
        (:func:`~monodbh.toolkit.orientation.sideways_score` below it, gray levels) is flagged
        ``photo_maybe_sideways`` (docs/decisions/sideways-photo.md).
    edge_mask_zoom : the mask that guides the search for the roped stem's edges at the rope comes
        from a second segmenter pass on a square crop around the rope, this fraction of the working
        image's long side (None: the whole photo's mask; docs/decisions/zoomed-edge-mask.md).
    row_marker_max_px : with the marker's width known, a rope found only as a faint red row across
        a trunk (the stem search) is refused where the marker at the measured distance would be
        this many working-image pixels thick or more: the band detector sees so thick a marker as
        a line (None: no check; docs/decisions/stem-search.md).
    max_marker_width_m, max_dbh_cm : a result is refused as implausible where the widest marker
        supported (a 50 mm strap) would be under one photo pixel thick at its distance (no rope is
        seen there), or where its DBH is over this (docs/decisions/taps.md).
    rope : the rope cascade's parameters (:class:`~monodbh.toolkit.rope.config.RopeConfig`).
    geometry : the geometry's parameters (:class:`~monodbh.toolkit.geometry.config.GeometryConfig`):
        up direction, stem base, scale candidates and their combination, sigma, DBH.
    """
    work_long_side_px: int = 1600
    rope_full_resolution: bool = True
    marker_edges: bool = True
    overlap_networks: bool = True
    depth_mirror_average: bool = True
    stem_base_threshold: float = 0.7
    edge_network: bool = True
    ort_spin: bool = field(default_factory=lambda: os.environ.get("MONODBH_ORT_SPIN", "0") == "1")
    sideways_score_max: float = -60.0
    edge_mask_zoom: float | None = 0.3
    row_marker_max_px: float | None = 4.0
    max_marker_width_m: float = 0.05
    max_dbh_cm: float = 500.0
    rope: RopeConfig = field(default_factory=RopeConfig)
    geometry: GeometryConfig = field(default_factory=GeometryConfig)

    def __post_init__(self) -> None:
        if self.edge_mask_zoom is not None and not 0.0 < self.edge_mask_zoom <= 1.0:
            raise ValueError(f"edge_mask_zoom must be in (0, 1] or None, got {self.edge_mask_zoom}")
