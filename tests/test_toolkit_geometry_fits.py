"""Low-level geometry (toolkit.geometry.fits): circle fits on partial arcs, planes, metrology, tangent-ray DBH."""
import numpy as np
import pytest

from monodbh.toolkit.geometry.fits import (fit_circle, fit_plane_ransac, metrology_distance, normalize, pixel_rays,
                                           tangent_diameter)


@pytest.mark.parametrize("arc_deg", [90, 120, 180, 270])
def test_circle_fit_partial_arc_is_unbiased(arc_deg):
    rng = np.random.default_rng(1)
    r, c = 0.15, np.array([0.3, 5.0])
    t = np.linspace(-np.radians(arc_deg) / 2, np.radians(arc_deg) / 2, 80) - np.pi / 2
    P = c + r * np.c_[np.cos(t), np.sin(t)] + rng.normal(0, 0.0015, (80, 2))
    # outliers (bark flakes, background) must not matter
    P = np.concatenate([P, c + rng.uniform(-0.5, 0.5, (12, 2))])
    f = fit_circle(P, threshold=0.005)
    assert f
    assert f.r == pytest.approx(r, rel=0.03 if arc_deg >= 120 else 0.06)
    assert np.hypot(f.xc - c[0], f.yc - c[1]) < 0.01
    assert abs(f.arc_deg - arc_deg) < 15


def test_circle_fit_failure_is_falsy():
    f = fit_circle(np.zeros((3, 2)), threshold=0.01)
    assert not f and "slice points" in f.reason


def test_plane_ransac_recovers_ground_with_outliers():
    rng = np.random.default_rng(0)
    n = normalize(np.array([0.05, -1.0, 0.2]))       # camera frame: up is -y
    h = 1.5
    # points on n.X + h = 0
    a = normalize(np.cross(n, [1, 0, 0]))
    b = np.cross(n, a)
    uv = rng.uniform(-5, 5, (500, 2))
    P = -h * n + uv[:, :1] * a + uv[:, 1:] * b + rng.normal(0, 0.01, (500, 3))
    P = np.concatenate([P, rng.uniform(-5, 5, (150, 3))])
    pl = fit_plane_ransac(P, threshold=0.03)
    assert pl
    assert abs(abs(pl.n @ n) - 1) < 1e-3
    assert pl.c == pytest.approx(h, abs=0.01)


def test_metrology_recovers_distance():
    up = normalize(np.array([0.0, -1.0, 0.05]))
    base = np.array([0.4, 1.5, 6.0])
    top = base + 1.3 * up
    lt, lb, res = metrology_distance(normalize(top), normalize(base), up, 1.3)
    assert lt == pytest.approx(np.linalg.norm(top), rel=1e-9)
    assert lb == pytest.approx(np.linalg.norm(base), rel=1e-9)
    assert res < 1e-9


def test_tangent_diameter_of_a_cylinder():
    axis = normalize(np.array([0.02, -1.0, 0.01]))
    C = np.array([0.3, 0.2, 5.0])
    rho = 0.17
    # tangent points of the circle seen from the origin, in the cross-section plane
    Cp = C - (C @ axis) * axis
    D = np.linalg.norm(Cp)
    e1 = Cp / D
    e2 = np.cross(axis, e1)
    ang = np.arcsin(rho / D)
    rays = [np.cos(ang) * e1 + s * np.sin(ang) * e2 + 0.1 * axis for s in (-1, 1)]
    assert tangent_diameter(rays[0], rays[1], axis, C) == pytest.approx(2 * rho, rel=1e-9)


def test_pixel_rays_of_a_pinhole_camera():
    from monodbh.calib import Camera
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    cam = Camera(K, None, (640, 480))
    r = pixel_rays(cam, np.array([[320.0, 240.0], [820.0, 240.0]]))
    assert r.shape == (2, 3)
    np.testing.assert_allclose(r[0], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(r[1], normalize(np.array([1.0, 0, 1])), atol=1e-9)
    assert pixel_rays(cam, (320.0, 240.0)).shape == (1, 3)
