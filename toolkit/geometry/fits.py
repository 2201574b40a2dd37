"""Low-level metric geometry of one stem: rays, planes, single-view metrology, tangent-ray and circle fits.

Imported by the stages of :mod:`monodbh.toolkit.geometry` (and by anything that needs these
primitives); imports numpy (scipy and scikit-image inside :func:`fit_circle`). All functions work
in the camera frame (OpenCV: x right, y down, z forward), metres. Fitting functions return falsy
result objects instead of raising (scikit-image style).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "normalize", "rays_from_normalized", "pixel_rays", "PlaneFit", "fit_plane_ransac", "metrology_distance",
    "tangent_diameter", "CircleFit", "fit_circle", "project_perpendicular",
]


def normalize(v: np.ndarray) -> np.ndarray:
    """Unit vectors along the last axis, ``(..., 3)``."""
    v = np.asarray(v, np.float64)
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-15)


def rays_from_normalized(xy: np.ndarray) -> np.ndarray:
    """Unit rays ``(N, 3)`` through undistorted normalized image coordinates ``(N, 2)``."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    return normalize(np.concatenate([xy, np.ones((len(xy), 1))], 1))


def pixel_rays(camera, xy) -> np.ndarray:
    """Unit rays ``(N, 3)`` through image pixels ``xy`` ``(N, 2)`` (or ``(2,)``) of ``camera``
    (a :class:`monodbh.calib.Camera`: its lens distortion is undone first)."""
    nxy = camera.undistort_points(np.asarray(xy, np.float64).reshape(-1, 2), normalized=True)
    return rays_from_normalized(nxy)


def project_perpendicular(v: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Component of vectors ``(N, 3)`` perpendicular to the unit ``axis`` ``(3,)``."""
    v = np.asarray(v, np.float64)
    return v - (v @ axis)[..., None] * axis


@dataclass
class PlaneFit:
    """Plane ``n . X + c = 0`` with unit normal ``n`` (3,) pointing towards the camera side.

    Falsy when the fit failed (``n`` is None).
    """
    n: np.ndarray | None = None
    c: float = 0.0
    inlier_ratio: float = 0.0
    rms_m: float = np.inf
    reason: str = ""

    def __bool__(self) -> bool:
        return self.n is not None

    def height(self, X: np.ndarray) -> np.ndarray:
        """Signed distance of points ``(N, 3)`` above the plane (positive on the camera side)."""
        return np.asarray(X) @ self.n + self.c


def fit_plane_ransac(points: np.ndarray, *, threshold: float, max_trials: int = 200,
                     rng: np.random.Generator | int | None = 0, min_points: int = 30) -> PlaneFit:
    """Robust plane through ``points`` ``(N, 3)``: RANSAC on 3-point samples, then a
    least-squares refit on the inliers.

    Parameters
    ----------
    threshold : inlier distance (same unit as the points).

    Returns
    -------
    PlaneFit (falsy with ``reason`` when there are too few points or no consensus).

    Examples
    --------
    >>> P = np.c_[np.random.default_rng(0).uniform(-1, 1, (100, 2)), np.zeros(100)]
    >>> bool(fit_plane_ransac(P + [0, 0, 2.0], threshold=0.01))
    True
    """
    P = np.asarray(points, np.float64).reshape(-1, 3)
    P = P[np.isfinite(P).all(1)]
    if len(P) < min_points:
        return PlaneFit(reason=f"only {len(P)} ground points")
    rng = np.random.default_rng(rng)
    best, best_n = None, -1
    idx = rng.integers(0, len(P), (max_trials, 3))
    A, B, C = P[idx[:, 0]], P[idx[:, 1]], P[idx[:, 2]]
    N = np.cross(B - A, C - A)
    ok = np.linalg.norm(N, axis=1) > 1e-12
    N = normalize(N[ok])
    cs = -(N * A[ok]).sum(1)
    # evaluate in chunks to bound memory
    for k in range(0, len(N), 50):
        d = np.abs(P @ N[k:k + 50].T + cs[k:k + 50])
        cnt = (d < threshold).sum(0)
        j = int(np.argmax(cnt))
        if cnt[j] > best_n:
            best_n, best = int(cnt[j]), (N[k + j], cs[k + j])
    if best is None or best_n < 3:
        return PlaneFit(reason="no plane consensus")
    n, c = best
    inl = np.abs(P @ n + c) < threshold
    Q = P[inl]
    mu = Q.mean(0)
    _, _, vt = np.linalg.svd(Q - mu, full_matrices=False)
    n = vt[-1]
    c = -n @ mu
    if c < 0:          # camera (origin) on the positive side
        n, c = -n, -c
    res = Q @ n + c
    return PlaneFit(n=n, c=float(c), inlier_ratio=float(inl.mean()), rms_m=float(np.sqrt(np.mean(res ** 2))))


def metrology_distance(ray_top: np.ndarray, ray_base: np.ndarray, up: np.ndarray,
                       height_m: float = 1.3) -> tuple[float, float, float]:
    """Single-view metrology of a vertical segment of known length.

    Finds depths along the unit rays so that ``l_top * ray_top - l_base * ray_base = height_m * up``
    (least squares; the three vectors are coplanar when the segment is along ``up``).

    Parameters
    ----------
    ray_top, ray_base : (3,) unit rays through the top (rope) and base points of the segment.
    up : (3,) unit direction of the segment, base -> top.

    Returns
    -------
    (l_top, l_base, residual_m) in metres along the rays; non-positive depths mean failure.
    """
    A = np.stack([ray_top, -ray_base], 1)
    b = height_m * np.asarray(up, np.float64)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    res = float(np.linalg.norm(A @ sol - b))
    return float(sol[0]), float(sol[1]), res


def tangent_diameter(ray_left: np.ndarray, ray_right: np.ndarray, axis_dir: np.ndarray,
                     axis_point: np.ndarray) -> float:
    """Diameter of a circular stem from its two silhouette tangent rays.

    In the cross-section plane (perpendicular to ``axis_dir``), the tangent rays from the
    camera to a circle of radius ``rho`` whose centre lies at distance ``D`` subtend
    ``alpha = 2 asin(rho / D)``, so ``diameter = 2 D sin(alpha / 2)``.

    Parameters
    ----------
    ray_left, ray_right : (3,) rays through the two silhouette edges at the same height.
    axis_dir : (3,) unit stem direction.
    axis_point : (3,) a point of the stem axis at that height (camera frame, metres).
    """
    a = normalize(project_perpendicular(np.asarray(ray_left, float), axis_dir))
    b = normalize(project_perpendicular(np.asarray(ray_right, float), axis_dir))
    alpha = float(np.arccos(np.clip(a @ b, -1.0, 1.0)))
    D = float(np.linalg.norm(project_perpendicular(np.asarray(axis_point, float), axis_dir)))
    return 2.0 * D * np.sin(alpha / 2.0)


@dataclass
class CircleFit:
    """Circle ``(xc, yc, r)``; falsy on failure. ``arc_deg`` is the angular coverage of inliers."""
    xc: float = np.nan
    yc: float = np.nan
    r: float = np.nan
    inlier_ratio: float = 0.0
    rms: float = np.inf
    arc_deg: float = 0.0
    reason: str = ""

    def __bool__(self) -> bool:
        return bool(np.isfinite(self.r) and self.r > 0)


def fit_circle(xy: np.ndarray, *, threshold: float, rng: int | None = 0, max_trials: int = 300,
               r_max: float | None = None) -> CircleFit:
    """Robust circle fit: ``skimage.measure.ransac`` with ``CircleModel``, then a geometric
    (orthogonal distance) least-squares refinement on the inliers.

    Algebraic fits are biased on short arcs; the geometric refinement is not.

    Parameters
    ----------
    xy : (N, 2) points.
    threshold : RANSAC residual threshold (same unit).
    r_max : reject circles larger than this.

    Returns
    -------
    CircleFit (falsy with ``reason`` on failure).

    Examples
    --------
    >>> t = np.linspace(0, np.pi, 50)
    >>> f = fit_circle(np.c_[np.cos(t), np.sin(t)] * 0.2 + 1.0, threshold=0.005)
    >>> round(f.r, 3)
    0.2
    """
    from scipy.optimize import least_squares
    from skimage.measure import CircleModel, ransac

    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    xy = xy[np.isfinite(xy).all(1)]
    if len(xy) < 5:
        return CircleFit(reason=f"only {len(xy)} slice points")

    def valid(model, *data):
        r = getattr(model, "radius", None)
        if r is None or not np.isfinite(r):
            return False
        return r_max is None or r < r_max

    try:
        model, inl = ransac(xy, CircleModel, min_samples=3, residual_threshold=threshold,
                            max_trials=max_trials, rng=rng, is_model_valid=valid)
    except Exception as e:  # noqa: BLE001 - degenerate input
        return CircleFit(reason=f"ransac failed: {e}")
    if model is None or inl is None or inl.sum() < 5:
        return CircleFit(reason="no circle consensus")
    P = xy[inl]
    x0 = np.array([*model.center, model.radius], np.float64)

    def res(p):
        return np.hypot(P[:, 0] - p[0], P[:, 1] - p[1]) - p[2]

    sol = least_squares(res, x0, loss="soft_l1", f_scale=threshold)
    xc, yc, r = sol.x
    if not np.isfinite(r) or r <= 0 or (r_max is not None and r > r_max):
        return CircleFit(reason="refinement diverged")
    ang = np.sort(np.arctan2(P[:, 1] - yc, P[:, 0] - xc))
    gaps = np.diff(np.r_[ang, ang[0] + 2 * np.pi])
    arc = 360.0 - np.degrees(gaps.max())
    return CircleFit(xc=float(xc), yc=float(yc), r=float(abs(r)), inlier_ratio=float(inl.mean()),
                     rms=float(np.sqrt(np.mean(res(sol.x) ** 2))), arc_deg=float(arc))
