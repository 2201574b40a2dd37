"""Rope finding: the red measuring rope tied around a stem at breast height, found by one of
three detectors; imported by the pipeline, the measuring geometry (red-ness), the overlay and
the rope benchmarks and fitters. Imports numpy and OpenCV only (scipy lazily, in the stem search).

Modules, one concept each:

- :mod:`.detection` -- :class:`RopeCandidate`, :class:`RopeDetection` (what every detector returns);
- :mod:`.config` -- :class:`BandConfig`, :class:`StemSearchConfig`, :class:`FinderConfig`,
  :class:`RopeConfig` (every tuning parameter, documented);
- :mod:`.redness` -- red-ness maps and the thin-line contrast;
- :mod:`.band` -- the classical band detector :func:`detect_rope`, with its pieces and bands
  (:mod:`.band_segments`), features and score (:mod:`.band_features`) and full-resolution
  refinement (:mod:`.band_refine`);
- :mod:`.profile` -- the rope's thickness from its red-ness profile;
- :mod:`.stem_search` -- the mask-guided stem-profile search and its rope-verifier glue;
- :mod:`.finder` -- the rope from the mask-free rope finder network, and its cross-check;
- :mod:`.select` -- :func:`select_rope`, the cascade: which detector's rope is measured, or why
  none is (:class:`RopeChoice`, :class:`RopeSource`, :class:`Refusal`);
- :mod:`.ruler` -- the rope's thickness as a ruler, read on the full-resolution photo;
- :mod:`.geometry` -- distances to a rope band, the tree instance at a point;
- :mod:`.score` -- the linear log-odds score of the logistic models.
"""
from .band import detect_rope
from .config import BandConfig, FinderConfig, RopeConfig, StemSearchConfig
from .detection import RopeCandidate, RopeDetection
from .finder import band_shaped, finder_check, finder_support, rope_from_finder
from .geometry import distance_to_band, distance_to_chord, distance_to_vertices, instance_at_or_near, instance_in_window
from .profile import rope_profile_fwhm
from .redness import line_contrast, red_shift_map, redness_map
from .score import linear_score
from .select import Refusal, RopeChoice, RopeSource, rope_across_trunk, select_rope
from .stem_search import StemBand, detect_rope_on_stems, stem_band_score, stem_bands, stem_evidence_choice, trunk_like

__all__ = ["RopeCandidate", "RopeDetection", "BandConfig", "StemSearchConfig", "FinderConfig",
           "detect_rope", "redness_map", "red_shift_map", "line_contrast", "rope_profile_fwhm",
           "StemBand", "stem_bands", "trunk_like", "stem_band_score", "stem_evidence_choice", "detect_rope_on_stems",
           "rope_from_finder", "band_shaped", "finder_support", "finder_check",
           "distance_to_vertices", "distance_to_chord", "distance_to_band", "instance_in_window",
           "instance_at_or_near", "linear_score",
           "RopeConfig", "select_rope", "RopeChoice", "RopeSource", "Refusal", "rope_across_trunk"]
