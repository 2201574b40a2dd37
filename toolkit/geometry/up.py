"""The up direction (its sources and which one is used) and the roped stem's direction and axis ray.

Imported by :mod:`.measure` and :mod:`.stem_base`; imports :mod:`.fits` and :mod:`.vanishing`.
The sources of "up", best first (:attr:`~.config.UpConfig.priority`): the calibrated pose
(cam.yaml), the vertical vanishing point of the photo's near-vertical lines, the depth map's
ground plane (added by :mod:`.measure`), the image's vertical. The stem's direction is up
constrained to the plane through the camera centre and the stem's image mid-line (decision record
``docs/decisions/stem-direction.md``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..result import MeasureResult
from .config import UpConfig, VanishingConfig
from .edges import TrunkEdges
from .fits import normalize, pixel_rays, project_perpendicular
from .perception import Perception
from .vanishing import vertical_direction

__all__ = ["StemAxis", "photo_up_sources", "vertical_hint", "choose_up", "stem_axis", "stem_image_direction"]


@dataclass
class StemAxis:
    """The roped stem at the rope in the camera frame (unit vectors (3,)).

    Attributes
    ----------
    r_L, r_R : rays through the left and right edges at the rope.
    r_mid : ray through the edges' midpoint; mid_xy : (2,) that midpoint (pixels).
    up : the up direction used (pointing up: y < 0).
    v : the stem's direction (up constrained to the plane of the camera centre and the stem's
        image mid-line: the visible lean is kept).
    r_A : ray through the stem's axis at the rope (the tangent rays' bisector in the cross-section).
    sin_half : sine of half the angle the stem subtends in the cross-section.
    """
    r_L: np.ndarray
    r_R: np.ndarray
    r_mid: np.ndarray
    mid_xy: np.ndarray
    up: np.ndarray
    v: np.ndarray
    r_A: np.ndarray
    sin_half: float


def photo_up_sources(perc: Perception, gray: np.ndarray, res: MeasureResult,
                     config: VanishingConfig | None = None) -> dict[str, np.ndarray]:
    """The up directions that need no depth map: ``{"pose": (3,)}`` from the calibrated pose, else
    ``{"vanishing": (3,)}`` from the vertical vanishing point (pinhole photos with
    ``perc.use_vanishing``; its time goes to ``res.timings_ms["vanishing"]``, the estimate to
    ``res.debug["vanishing"]``), or neither. ``gray`` (H, W) float32 intensity of ``perc.rgb``."""
    cam = perc.camera
    up_sources = {}
    if getattr(cam, "pose", None) is not None:
        R = np.asarray(cam.pose.R_world_from_camera)
        up_sources["pose"] = R.T @ np.array([0, 0, 1.0])
    if perc.use_vanishing and "pose" not in up_sources and not np.any(np.asarray(cam.dist) != 0):
        # independent of the depth network (the vertical vanishing point of trunk edges)
        t_vp = time.perf_counter()
        vp = vertical_direction(np.clip(gray, 0, 255).astype(np.uint8), np.asarray(cam.K, float), config=config)
        res.timings_ms["vanishing"] = 1000 * (time.perf_counter() - t_vp)
        if vp:
            up_sources["vanishing"] = vp.up
            res.debug["vanishing"] = vp
    return up_sources


def vertical_hint(up_sources: dict) -> np.ndarray | None:
    """(3,) the pose's up, else the vanishing point's, else None (the up directions that do not
    come from the depth map)."""
    return up_sources.get("pose", up_sources.get("vanishing"))


def choose_up(up_sources: dict, flags: list[str], res: MeasureResult, config: UpConfig | None = None) -> np.ndarray:
    """The (3,) up direction of the first source of ``config.priority`` in ``up_sources`` (the
    image's vertical, flagged ``up_from_image``, when there is none), pointing up; the sources and
    the one used go to ``res.debug`` (``up_sources``, ``up_source``)."""
    cfg = config or UpConfig()
    if not up_sources:
        # last resort: the camera assumed level (up = -y); the stem direction keeps its image
        # lean (up projected into the stem's mid-line plane)
        up_sources["image"] = np.array([0.0, -1.0, 0.0])
        flags.append("up_from_image")
    up = next(up_sources[k] for k in cfg.priority if k in up_sources)
    if up[1] > 0:
        up = -up
    res.debug["up_sources"] = {k: np.asarray(u_, float) for k, u_ in up_sources.items()}
    res.debug["up_source"] = next(k for k in cfg.priority if k in up_sources)
    return up


def stem_axis(camera, edges: TrunkEdges, up: np.ndarray) -> StemAxis:
    """The stem's direction and axis ray at the rope from its edges (:class:`~.edges.TrunkEdges`)
    and the (3,) ``up`` direction, through ``camera`` (:class:`monodbh.calib.Camera`)."""
    r_L, r_R = pixel_rays(camera, np.stack([edges.left_xy, edges.right_xy]))
    mid_xy = 0.5 * (edges.left_xy + edges.right_xy)
    # plane through the camera centre and the stem's image mid-line
    p_lo = mid_xy + 50.0 * edges.along
    r_mid, r_lo = pixel_rays(camera, np.stack([mid_xy, p_lo]))
    n_axis_plane = normalize(np.cross(r_mid, r_lo))
    # stem direction: up projected into the mid-line plane (keeps the visible lean)
    v = normalize(up - (up @ n_axis_plane) * n_axis_plane)
    if v @ up < 0:
        v = -v
    # axis ray at the rope: bisector of the tangent rays in the cross-section
    a = normalize(project_perpendicular(r_L, v))
    b = normalize(project_perpendicular(r_R, v))
    m = normalize(a + b)
    r_A = normalize(m * np.linalg.norm(project_perpendicular(r_mid, v)) + (r_mid @ v) * v)
    alpha = float(np.arccos(np.clip(a @ b, -1, 1)))
    return StemAxis(r_L=r_L, r_R=r_R, r_mid=r_mid, mid_xy=mid_xy, up=up, v=v, r_A=r_A, sin_half=np.sin(alpha / 2))


def stem_image_direction(cam, mid_xy, along, up_sources: dict, config: UpConfig | None = None) -> np.ndarray:
    """(2,) unit image direction down the stem at ``mid_xy``: the edges' ``along`` (2,) blended
    with the image of the vertical through ``mid_xy`` (towards the vertical vanishing point) when
    the pose or the vanishing point gives "up" (:attr:`~.config.UpConfig.stem_direction_edge_weight`).
    ``cam`` needs ``K`` only."""
    w = (config or UpConfig()).stem_direction_edge_weight
    a = np.asarray(along, np.float64)
    a = a / np.linalg.norm(a)
    up = vertical_hint(up_sources)
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
    b = w * a + (1 - w) * d
    return b / np.linalg.norm(b)
