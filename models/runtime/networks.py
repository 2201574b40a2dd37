"""The shipped networks loaded together (:func:`load_networks`), and the error model measured for them.

``models/manifest.json`` lists the shipped networks and the error model (per-source sigmas,
leading-source ranks, the distance calibration) that ``python -m monodbh.toolkit.error_model
FOLDER --write`` measured for exactly those files (their sha256) run as the pipeline runs them:
:func:`fresh_error_model` gives it only while that still holds. Imported by
``monodbh.toolkit.pipeline`` (its ``Session``), the error model's measuring code and the CLI;
imports the per-network modules of ``monodbh.models.runtime`` only.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from monodbh.models.runtime.common import MODELS_DIR, MonodbhError, load_manifest
from monodbh.models.runtime.depth import DepthPredictor
from monodbh.models.runtime.rope_finder import RopeFinder
from monodbh.models.runtime.rope_verifier import RopeVerifier
from monodbh.models.runtime.segmenter import Segmenter
from monodbh.models.runtime.stem_base import StemBaseFinder, StemBaseNetFinder
from monodbh.models.runtime.stem_edge import StemEdgeFinder
from monodbh.models.runtime.tree import TreePredictor

__all__ = ["ERROR_MODEL_KINDS", "fresh_error_model", "Networks", "load_networks"]

#: the networks the measured error model depends on (those of them that are shipped; the two
#: stem-base networks are optional; the rope verifier and the rope finder only decide which photos
#: are measured, not how well, so they are not among them)
ERROR_MODEL_KINDS: tuple[str, ...] = ("segmenter", "depth", "tree", "stem_base", "stem_base_net")


def fresh_error_model(manifest: dict[str, Any], depth_flip_tta: bool = True) -> dict[str, Any]:
    """``manifest["error_model"]`` when it was measured for exactly the shipped networks.

    Parameters
    ----------
    manifest : dict
        A manifest as :func:`~monodbh.models.runtime.common.load_manifest` returns it.
    depth_flip_tta : bool
        Whether the depth network is run with mirror-image averaging now (the error model
        records how it was run when measured).

    Returns
    -------
    dict
        The error model (``sigma``, ``rank``, ``distance_calibration``, ...) when its ``models``
        are the sha256 of the shipped :data:`ERROR_MODEL_KINDS` and its ``depth_flip_tta``
        matches; else ``{}`` (stale after retraining, or never measured).
    """
    em = manifest.get("error_model") or {}
    models = manifest.get("models", {})
    shipped = {k: (models.get(k) or {}).get("sha256") for k in ERROR_MODEL_KINDS if k in models}
    fresh = (em.get("sigma") is not None and em.get("models") == shipped
             and bool(em.get("depth_flip_tta", False)) == depth_flip_tta)
    return em if fresh else {}


@dataclass(frozen=True)
class Networks:
    """The loaded networks and the error model measured for them (:func:`load_networks`).

    Attributes
    ----------
    segmenter : Segmenter
    depth : DepthPredictor
    tree : TreePredictor
    stem_base : StemBaseFinder or None
        None when none is shipped (the edge tracker then looks for the stem base alone); its
        ``second`` is the second stem-base network (:class:`StemBaseNetFinder`) where shipped.
    stem_edge : StemEdgeFinder or None
        None when none is shipped (the stem's edges are then the photo's gradients near the mask's).
    rope_verifier : RopeVerifier or None
        None when none is shipped (the stem search's own score then decides).
    rope_finder : RopeFinder or None
        None when none is shipped.
    models_dir : Path
        Folder the networks were loaded from.
    sigma : dict or None
        The error model's per-source 1-sigma (relative), None without a fresh error model.
    rank : dict or None
        The error model's leading-source ranks (typical relative errors), None without one.
    distance_calibration : dict or None
        The error model's calibration of network-led distances, None without one.
    error_model_stale : bool
        The manifest holds an error model, but not one measured for these networks run so.
    trunk_net : Path or None
        The trunk network's file (:class:`~.trunk_net.TrunkNet`), loaded only where a trunk map
        is asked for; None when none is shipped.
    """

    segmenter: Segmenter
    depth: DepthPredictor
    tree: TreePredictor
    stem_base: StemBaseFinder | None
    stem_edge: StemEdgeFinder | None
    rope_verifier: RopeVerifier | None
    rope_finder: RopeFinder | None
    models_dir: Path
    sigma: dict[str, float] | None
    rank: dict[str, float] | None
    distance_calibration: dict[str, Any] | None
    error_model_stale: bool
    trunk_net: Path | None = None


def _required(models: dict[str, Any], mdir: Path, kind: str) -> Path:
    """The file of a network the pipeline cannot do without (a user error when it is missing)."""
    entry = models.get(kind)
    if not entry:
        raise MonodbhError(f"{mdir / 'manifest.json'}: no shipped '{kind}' model "
                           f"(train it with 'dbh train' and 'dbh export RUN_DIR --ship')")
    p = mdir / entry["file"]
    if not p.exists():
        raise MonodbhError(f"{p}: model file missing")
    return p


def _optional(models: dict[str, Any], mdir: Path, kind: str) -> Path | None:
    """The file of an optional network, None when none is shipped; a manifest entry whose file is
    missing is an error (a half-copied models folder must not silently measure without it)."""
    entry = models.get(kind)
    if not entry:
        return None
    p = mdir / entry["file"]
    if not p.exists():
        raise MonodbhError(f"{p}: model file missing (listed in {mdir / 'manifest.json'})")
    return p


def _models_folder(models_dir: str | Path) -> Path:
    """``models_dir`` checked: an existing folder (a one-line error otherwise, never the shipped
    models instead)."""
    mdir = Path(models_dir)
    if not str(models_dir).strip():
        raise MonodbhError("--models-dir is empty (leave it out for the shipped models)")
    if not mdir.exists():
        raise MonodbhError(f"{mdir}: no such folder (--models-dir)")
    if not mdir.is_dir():
        raise MonodbhError(f"{mdir}: not a folder (--models-dir)")
    return mdir


def load_networks(models_dir: str | Path | None = None, *, threads: int = 2, depth_flip_tta: bool = True,
                  stem_base_threshold: float = 0.7, spin: bool = False) -> Networks:
    """Load the shipped networks of ``models_dir`` and the error model measured for them.

    Parameters
    ----------
    models_dir : path, optional
        Folder with ``manifest.json`` and the ``*.onnx`` files; default the shipped models
        inside the package (:data:`~monodbh.models.runtime.common.MODELS_DIR`).
    threads : int
        onnxruntime intra-op threads per network (``docs/decisions/threads.md``).
    depth_flip_tta : bool
        Run the depth network on the photo and its mirror image (``docs/decisions/threads.md``,
        mirror averaging); the error model is fresh only if it was measured so.
    stem_base_threshold : float
        The stem-base network's probability needed to report a base (``docs/decisions/stem-base.md``).
    spin : bool
        onnxruntime's idle threads spin instead of sleeping
        (:func:`~monodbh.models.runtime.common.session_options`).

    Returns
    -------
    Networks

    Raises
    ------
    MonodbhError
        The folder has no manifest, or the segmenter, depth or tree network is not shipped or
        its file is missing.
    """
    mdir = MODELS_DIR if models_dir is None else _models_folder(models_dir)
    if not (mdir / "manifest.json").exists():
        raise MonodbhError(f"{mdir}: no models here (no manifest.json; a models folder holds the "
                           f"files of 'dbh export --ship')")
    manifest = load_manifest(mdir / "manifest.json")
    models = manifest.get("models", {})
    opts = dict(threads=threads, spin=spin)
    stem_base = _optional(models, mdir, "stem_base")
    base_net = _optional(models, mdir, "stem_base_net")
    second = None if base_net is None else StemBaseNetFinder(base_net, manifest=manifest,
                                                             threshold=stem_base_threshold, **opts)
    stem_edge = _optional(models, mdir, "stem_edge")
    rope_verifier = _optional(models, mdir, "rope_verifier")
    rope_finder = _optional(models, mdir, "rope_finder")
    trunk_head = _optional(models, mdir, "trunk_head")      # loaded only where a trunk map is asked for
    trunk_net = _optional(models, mdir, "trunk_net")        # the same
    em = fresh_error_model(manifest, depth_flip_tta)
    return Networks(
        segmenter=Segmenter(_required(models, mdir, "segmenter"), manifest=manifest, trunk_head=trunk_head, **opts),
        depth=DepthPredictor(_required(models, mdir, "depth"), flip_tta=depth_flip_tta, **opts),
        tree=TreePredictor(_required(models, mdir, "tree"), **opts),
        stem_base=second if stem_base is None else StemBaseFinder(stem_base, manifest=manifest,
                                                                  threshold=stem_base_threshold,
                                                                  second=second, **opts),
        stem_edge=None if stem_edge is None else StemEdgeFinder(stem_edge, manifest=manifest, **opts),
        rope_verifier=None if rope_verifier is None else RopeVerifier(rope_verifier, manifest=manifest, **opts),
        rope_finder=None if rope_finder is None else RopeFinder(rope_finder, manifest=manifest, **opts),
        models_dir=mdir,
        sigma=em.get("sigma"),
        rank=em.get("rank"),
        distance_calibration=em.get("distance_calibration"),
        error_model_stale=bool(manifest.get("error_model")) and not em,
        trunk_net=trunk_net,
    )
