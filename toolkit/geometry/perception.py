"""The geometry's input: :class:`Perception`, everything the geometry needs in one image frame.

Built by the measuring pipeline (:mod:`monodbh.toolkit.pipeline`, network perception) and by
ground-truth perception (:mod:`monodbh.toolkit.evaluation.ground_truth`); read by every stage of
:mod:`monodbh.toolkit.geometry`. Plain data: it imports numpy only.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Perception"]


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
    extra : other facts about the perception: ``"tree_mask_from_rope"`` (bool) when the tree
        mask is the rope band's (no segmented stem confirms where tracked edges end).
    The other fields are described where they are declared.
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
    edge_finder: object = None      # callable(rgb, center_xy, along, width_px) -> EdgeEstimate (the stem-edge network) or None
    rope_length_px: float | None = None  # length of the rope band across the stem (pixels)
    rope_polyline: np.ndarray | None = None  # (N, 2) the rope's centre line across the stem (pixels)
    rope_band_mask: np.ndarray | None = None  # (H, W) bool band as wide as the rope's extent
    rope_thickness_px: float | None = None  # the rope's measured thickness (FWHM across the band, pixels)
    rope_thickness_native_px: float | None = None  # the same in the pixels it was measured in (full resolution)
    rope_contrast: float | None = None      # red-ness contrast of the rope's mean profile across the band
    rope_thickness_edges: bool = False      # the thickness is edge to edge (else a half-maximum width)
    rope_diameter_m: float | None = None    # the rope's true diameter, given by the user (``--rope-mm``)
    use_vanishing: bool = True      # estimate "up" from the vertical vanishing point (no pose)
    sigma_network: dict | None = None  # measured error model of the shipped networks (manifest)
    rank_network: dict | None = None   # their typical errors, which pick the leading scale source
    distance_calibration: dict | None = None  # {"a", "b", "sigma"}: ln d -> a + b ln d for network-led scales
    extra: dict = field(default_factory=dict)
