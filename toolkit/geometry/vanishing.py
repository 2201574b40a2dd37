"""The "up" direction from the vertical vanishing point of trunk edges (classical vision).

Imported by :mod:`.up` (the up direction without a calibrated pose); imports numpy and cv2
(``cv2.ximgproc``). Tree stems stand close to vertical (a few degrees of lean, in random
directions), so the long, near-vertical straight edges of a forest photo (trunk silhouettes, bark
furrows) meet near the vertical vanishing point. Its direction in the camera frame is the world's
"up", without a calibrated pose and without the depth network. Parameters:
:class:`~.config.VanishingConfig` (decision record ``docs/decisions/stem-direction.md``).

Method (:func:`vertical_direction`):

1. Line segments with OpenCV's Fast Line Detector (``cv2.ximgproc``) on the grey image;
   kept when longer than ``min_len_frac`` of the image height and within ``max_tilt_deg``
   of the image's vertical.
2. Each segment spans an interpretation plane through the camera centre with unit normal
   ``n_i`` (cross product of its end-point rays); the vanishing direction ``u`` is
   perpendicular to all of them. RANSAC over segment pairs (``u = n_i x n_j``), scored by
   the length of the segments within ``inlier_deg``; then a weighted least-squares refinement
   (smallest right singular vector of ``W N``) with Cauchy weights.
3. The uncertainty: the angular scatter of the inlier segments around ``u`` divided by the
   square root of the number of independent stems (segments grouped by image column).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from .config import VanishingConfig

__all__ = ["VerticalEstimate", "vertical_direction", "line_segments"]

@dataclass
class VerticalEstimate:
    """Result of :func:`vertical_direction`; falsy when no direction was found.

    Attributes
    ----------
    up : (3,) unit vector in the camera frame (OpenCV: x right, y down), pointing up (y < 0).
    sigma_deg : 1-sigma angular uncertainty (degrees).
    n_segments, n_inliers, n_groups : segments considered / agreeing / distinct image columns.
    reason : why it failed (empty on success).
    """
    up: np.ndarray | None = None
    sigma_deg: float = np.inf
    n_segments: int = 0
    n_inliers: int = 0
    n_groups: int = 0
    reason: str = ""
    segments: np.ndarray | None = field(default=None, repr=False)   # (N, 4) inlier x1 y1 x2 y2

    def __bool__(self) -> bool:
        return self.up is not None

    @property
    def pitch_roll_deg(self) -> tuple[float, float]:
        """Camera pitch (positive = looking up) and roll (positive = turned clockwise as the
        photographer sees it) implied by ``up``, in the conventions of
        :class:`monodbh.calib.CameraPose`."""
        if self.up is None:
            return (np.nan, np.nan)
        u = self.up
        pitch = np.degrees(np.arcsin(np.clip(u[2], -1, 1)))        # looking up: up leans forward
        roll = np.degrees(np.arctan2(-u[0], -u[1]))
        return (float(pitch), float(roll))


def line_segments(gray: np.ndarray, min_len_px: float, config: VanishingConfig | None = None) -> np.ndarray:
    """Straight segments ``(N, 4)`` (x1, y1, x2, y2) of a uint8 / float grey image ``(H, W)``
    at least ``min_len_px`` long (and 10 px), with the line detector's parameters of ``config``."""
    cfg = config or VanishingConfig()
    g = gray if gray.dtype == np.uint8 else np.clip(gray, 0, 255).astype(np.uint8)
    fld = cv2.ximgproc.createFastLineDetector(length_threshold=int(max(10, min_len_px)),
                                              distance_threshold=cfg.line_distance_px,
                                              canny_th1=cfg.canny_thresholds[0], canny_th2=cfg.canny_thresholds[1],
                                              canny_aperture_size=3, do_merge=True)
    seg = fld.detect(g)
    if seg is None:
        return np.zeros((0, 4), np.float32)
    return seg.reshape(-1, 4).astype(np.float64)


def _normals(seg: np.ndarray, Kinv: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals of the segments' (N, 4) interpretation planes."""
    p1 = np.c_[seg[:, :2], np.ones(len(seg))] @ Kinv.T
    p2 = np.c_[seg[:, 2:], np.ones(len(seg))] @ Kinv.T
    n = np.cross(p1, p2)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _near_vertical(gray: np.ndarray, mask: np.ndarray | None, cfg: VanishingConfig) -> tuple[np.ndarray, np.ndarray]:
    """The photo's long near-vertical segments ``(N, 4)`` and their lengths ``(N,)`` (midpoint
    in ``mask`` (H, W) bool when given)."""
    H, W = gray.shape
    seg = line_segments(gray, cfg.min_len_frac * H, cfg)
    L = None
    if len(seg):
        d = seg[:, 2:] - seg[:, :2]
        L = np.hypot(d[:, 0], d[:, 1])
        tilt = np.degrees(np.arctan2(np.abs(d[:, 0]), np.abs(d[:, 1])))
        keep = (L >= cfg.min_len_frac * H) & (tilt <= cfg.max_tilt_deg)
        if mask is not None:
            mx = np.clip(((seg[:, 0] + seg[:, 2]) / 2).round().astype(int), 0, W - 1)
            my = np.clip(((seg[:, 1] + seg[:, 3]) / 2).round().astype(int), 0, H - 1)
            keep &= mask[my, mx]
        seg, L = seg[keep], L[keep]
    return seg, L


def _ransac_direction(N: np.ndarray, w: np.ndarray, cfg: VanishingConfig) -> np.ndarray | None:
    """The best-supported direction ``(3,)`` perpendicular to pairs of the (N, 3) plane normals
    (pairs drawn by the (N,) length weights ``w``), pointing up; None when no hypothesis is within
    ``cfg.max_from_level_deg`` of the level camera's up."""
    n_seg = len(N)
    thr = np.sin(np.radians(cfg.inlier_deg))
    rng = np.random.default_rng(cfg.seed)
    p = w / w.sum()
    level = np.array([0.0, -1.0, 0.0])
    # all RANSAC hypotheses at once: pairs drawn by length, u = n_i x n_j
    i = rng.choice(n_seg, cfg.iters, p=p)
    j = rng.choice(n_seg, cfg.iters, p=p)
    U = np.cross(N[i], N[j])
    nu = np.linalg.norm(U, axis=1)
    good = (i != j) & (nu > 1e-9)
    U = U[good] / nu[good, None]
    U *= np.where(U @ level < 0, -1.0, 1.0)[:, None]
    U = U[U @ level >= np.cos(np.radians(cfg.max_from_level_deg))]     # pitch / roll beyond any handheld photo
    if not len(U):
        return None
    support = (np.abs(N @ U.T) < thr).T.astype(np.float64) @ w      # (hypotheses,)
    return U[int(np.argmax(support))]


def _refine_direction(N: np.ndarray, w: np.ndarray, u: np.ndarray, cfg: VanishingConfig) -> np.ndarray:
    """Cauchy-weighted least squares of the direction ``u`` (3,) against the (N, 3) normals."""
    level = np.array([0.0, -1.0, 0.0])
    thr_r = np.sin(np.radians(cfg.refine_deg))
    for _ in range(cfg.refine_steps):
        r = N @ u
        cw = w / (1 + (r / thr_r) ** 2)
        _, _, Vt = np.linalg.svd(N * np.sqrt(cw)[:, None], full_matrices=False)
        u2 = Vt[-1]
        u = u2 if u2 @ level > 0 else -u2
    return u


def vertical_direction(gray: np.ndarray, K: np.ndarray, *, mask: np.ndarray | None = None,
                       config: VanishingConfig | None = None) -> VerticalEstimate:
    """Estimate the world's up direction in the camera frame from near-vertical image lines.

    Parameters
    ----------
    gray : (H, W) grey image of an undistorted (pinhole) photo.
    K : (3, 3) its intrinsics.
    mask : (H, W) bool, optional: only segments whose midpoint lies in it (e.g. tree pixels).
    config : :class:`~.config.VanishingConfig` (default when None): segment length and tilt,
        RANSAC and refinement angles, fewest stems.

    Returns
    -------
    VerticalEstimate (falsy with a reason when too few lines agree).

    Examples
    --------
    >>> import numpy as np
    >>> img = np.full((480, 640), 90, np.uint8)
    >>> for x in (100, 220, 340, 460, 560):
    ...     img[40:440, x:x + 30] = 200
    >>> K = np.array([[500., 0, 319.5], [0, 500., 239.5], [0, 0, 1]])
    >>> est = vertical_direction(img, K)
    >>> bool(est), round(float(est.up[1]), 3), round(float(abs(est.up[0])), 3)
    (True, -1.0, 0.0)
    """
    cfg = config or VanishingConfig()
    if gray.ndim != 2:
        raise ValueError(f"gray must be (H, W), got {gray.shape}")
    H, W = gray.shape
    seg, L = _near_vertical(gray, mask, cfg)
    n_seg = len(seg)
    if n_seg < 2 * cfg.min_groups:
        return VerticalEstimate(n_segments=n_seg, reason=f"too few near-vertical lines ({n_seg})")
    N = _normals(seg, np.linalg.inv(K))
    w = L / L.sum()
    u = _ransac_direction(N, w, cfg)
    if u is None:
        return VerticalEstimate(n_segments=n_seg, reason="no consistent vanishing direction")
    u = _refine_direction(N, w, u, cfg)
    r = N @ u
    inl = np.abs(r) < np.sin(np.radians(cfg.refine_deg))
    # distinct stems: inlier segment midpoints grouped in columns of the image width
    mid_x = (seg[inl, 0] + seg[inl, 2]) / 2
    groups = np.unique(np.floor(mid_x / (cfg.column_frac * W))).size
    if groups < cfg.min_groups:
        return VerticalEstimate(n_segments=n_seg, n_inliers=int(inl.sum()), n_groups=int(groups),
                                reason=f"near-vertical lines on too few stems ({groups})")
    # scatter of the agreeing lines (plane-to-direction angle), length-weighted
    ang = np.degrees(np.arcsin(np.clip(np.abs(r[inl]), 0, 1)))
    scatter = float(np.sqrt(np.average(ang ** 2, weights=w[inl])))
    # stems lean a few degrees each, shared by all their edges: the sigma falls with the number
    # of line columns, at least the lines' own scatter
    sigma = float(max(cfg.sigma_columns_deg / np.sqrt(groups), scatter))
    return VerticalEstimate(up=u, sigma_deg=sigma, n_segments=n_seg, n_inliers=int(inl.sum()),
                            n_groups=int(groups), segments=seg[inl].astype(np.float32))
