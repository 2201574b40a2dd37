"""monodbh.calib.Camera: rescaling, 90-degree turns (projection tests), undistortion, pose."""
import math

import cv2
import numpy as np
import pytest

from monodbh.calib import Camera, CameraFileError, CameraPose

K = np.array([[1000.0, 0, 655.3], [0, 990.0, 470.8], [0, 0, 1]])
DIST5 = np.array([-0.21, 0.09, 0.0031, -0.0017, -0.02])
# 12 coefficients: k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4 (rational + thin prism)
DIST12 = np.array([-0.2, 0.05, 0.002, -0.003, 0.01, 0.01, -0.02, 0.005, 0.001, -0.0005,
                   0.0015, 0.0007])


def _points(n=200, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-0.6, 0.6, (n, 3))
    X[:, 2] = rng.uniform(1.0, 3.0, n)
    return X


def _rotate_pixels(uv, w, h, rotation):
    """Where pixel (x, y) of a w x h image lands after cv2.rotate by ``rotation`` clockwise."""
    x, y = uv[:, 0], uv[:, 1]
    if rotation == 90:
        return np.stack([h - 1 - y, x], 1)
    if rotation == 180:
        return np.stack([w - 1 - x, h - 1 - y], 1)
    if rotation == 270:
        return np.stack([y, w - 1 - x], 1)
    return uv


def _rotate_points(X, rotation):
    M = np.linalg.matrix_power(np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]]), rotation // 90)
    return X @ M.T


@pytest.mark.parametrize("dist", [DIST5, DIST12], ids=["plumb_bob", "rational+prism"])
@pytest.mark.parametrize("rotation", [90, 180, 270])
def test_rotation_projection(dist, rotation):
    """A photo turned by cv2.rotate: the rotated camera must project to the turned pixels."""
    cam = Camera(K, dist, (1280, 960))
    X = _points()
    uv = cam.project(X)
    w2, h2 = (960, 1280) if rotation in (90, 270) else (1280, 960)
    rot = cam.for_image(w2, h2, rotation=rotation)
    got = rot.project(_rotate_points(X, rotation))
    assert np.abs(got - _rotate_pixels(uv, 1280, 960, rotation)).max() < 1e-9
    if rotation == 90:  # the documented closed form
        assert rot.fx == cam.fy and rot.fy == cam.fx
        assert rot.cx == pytest.approx(960 - 1 - cam.cy) and rot.cy == cam.cx
        assert rot.dist[2] == dist[3] and rot.dist[3] == -dist[2]


def test_rotation_with_real_image():
    """cv2.rotate of an image with a dot agrees with the rotated camera's projection."""
    cam = Camera(K, DIST5, (1280, 960))
    X = np.array([[0.31, -0.22, 1.4]])
    x, y = cam.project(X)[0]
    img = np.zeros((960, 1280), np.uint8)
    xi, yi = int(round(x)), int(round(y))
    img[yi, xi] = 255
    r = cv2.rotate(img, cv2.ROTATE_90_CLOCKWISE)
    ys, xs = np.nonzero(r)
    rot = cam.for_image(960, 1280)  # auto: landscape calibration -> 90 clockwise
    xr, yr = rot.project(_rotate_points(X, 90))[0]
    assert abs(xr - xs[0]) <= 0.5 + abs(y - yi) and abs(yr - ys[0]) <= 0.5 + abs(x - xi)


def test_rescale_pixel_centre_convention():
    cam = Camera(K, DIST5, (1280, 960))
    assert cam.for_image(1280, 960) is cam
    half = cam.for_image(640, 480)
    assert half.fx == pytest.approx(500.0) and half.fy == pytest.approx(495.0)
    assert half.cx == pytest.approx(0.5 * (655.3 + 0.5) - 0.5)
    assert half.cy == pytest.approx(0.5 * (470.8 + 0.5) - 0.5)
    assert np.array_equal(half.dist, cam.dist)
    X = _points()
    uv = cam.project(X)
    assert np.allclose(half.project(X), 0.5 * (uv + 0.5) - 0.5, atol=1e-9)
    # 4000x3000 -> 1333x1000 (rounded width) is still the same aspect ratio.
    big = Camera(np.array([[3000.0, 0, 2000], [0, 3000, 1500], [0, 0, 1]]), None, (4000, 3000))
    small = big.for_image(1333, 1000)
    assert small.fx == pytest.approx(3000 * 1333 / 4000) and small.fy == pytest.approx(1000.0)


def test_crop_refused():
    cam = Camera(K, DIST5, (1280, 960))
    for w, h in ((1280, 720), (960, 960), (1000, 960)):
        with pytest.raises(CameraFileError, match="crop") as ei:
            cam.for_image(w, h)
        assert "\n" not in str(ei.value)
    with pytest.raises(CameraFileError):
        cam.for_image(1280, 960, rotation=90)


def test_portrait_calibration_turns_counterclockwise():
    cam = Camera(K, DIST5, (1280, 960)).for_image(960, 1280, rotation=90)
    assert cam.image_rotation(1280, 960) == 270
    back = cam.for_image(1280, 960)
    assert np.allclose(back.K, K) and np.allclose(back.dist, DIST5)


def test_undistort_points_and_image():
    cam = Camera(K, DIST5, (1280, 960))
    X = _points()
    uv = cam.project(X)
    ideal = (X[:, :2] / X[:, 2:]) @ K[:2, :2].T + K[:2, 2]
    assert np.abs(cam.undistort_points(uv) - ideal).max() < 1e-6
    assert np.abs(cam.undistort_points(uv, normalized=True) - X[:, :2] / X[:, 2:]).max() < 1e-9
    # A bright dot at the distorted position appears at K_new * X in the undistorted image.
    P = np.array([[0.35, 0.25, 1.0]])
    x, y = cam.project(P)[0]
    img = np.zeros((960, 1280), np.float32)
    cv2.circle(img, (int(round(x * 16)), int(round(y * 16))), 3 * 16, 1.0, -1, cv2.LINE_AA, 4)
    out, K_new = cam.undistort_image(img, alpha=0.0)
    assert out.shape == img.shape and K_new.shape == (3, 3)
    ys, xs = np.mgrid[:960, :1280]
    m = out / out.sum()
    expected = K_new @ (P[0] / P[0, 2])
    assert abs((m * xs).sum() - expected[0]) < 0.15 and abs((m * ys).sum() - expected[1]) < 0.15
    with pytest.raises(ValueError, match="for_image"):
        cam.undistort_image(np.zeros((480, 640), np.uint8))


def test_input_checks():
    with pytest.raises(ValueError):
        Camera(np.eye(2), None, (10, 10))
    with pytest.raises(ValueError):
        Camera(K, np.zeros(6), (10, 10))
    with pytest.raises(ValueError):
        Camera(K, None, (0, 10))
    with pytest.raises(ValueError):
        Camera(K, None, (10, 10)).project(np.zeros((3, 2)))
    cam = Camera(K, None, (10, 10))
    assert cam.K.flags.writeable is False
    with pytest.raises(ValueError):
        cam.K[0, 0] = 1


def test_pose_conventions():
    """pitch > 0 looks up; roll > 0 dips the camera's right side; t = (0, 0, height)."""
    up = CameraPose.from_angles(1.6, 10.0, 0.0)
    assert up.R_world_from_camera[2, 2] > 0  # optical axis has a +z component
    assert up.height_m == 1.6 and up.pitch_deg == pytest.approx(10.0)
    rolled = CameraPose.from_angles(1.6, 0.0, 5.0)
    assert rolled.R_world_from_camera[2, 0] < 0  # camera x axis points down a little
    assert rolled.roll_deg == pytest.approx(5.0)
    p = CameraPose.from_angles(2.0, -35.0, 3.0, 20.0)
    assert (p.pitch_deg, p.roll_deg, p.yaw_deg) == pytest.approx((-35.0, 3.0, 20.0))
    R_cw, t_cw = p.camera_from_world()
    assert np.allclose(R_cw @ p.t_world_from_camera + t_cw, 0)
    # Level camera looks along world +x: a point ahead projects to the principal point.
    cam = Camera(K, None, (1280, 960), pose=CameraPose.from_angles(1.5, 0, 0))
    R_cw, t_cw = cam.pose.camera_from_world()
    Xc = R_cw @ np.array([5.0, 0.0, 1.5]) + t_cw
    assert np.allclose(cam.project(Xc[None])[0], K[:2, 2])
    # Ground points project below the principal point (y down).
    Xg = R_cw @ np.array([5.0, 0.0, 0.0]) + t_cw
    assert cam.project(Xg[None])[0, 1] > K[1, 2]
    with pytest.raises(ValueError):
        CameraPose(np.diag([1.0, 1.0, -1.0]), [0, 0, 1])


def test_pose_follows_photo_rotation():
    cam = Camera(K, DIST5, (1280, 960), pose=CameraPose.from_angles(1.5, -20.0, 2.0))
    rot = cam.for_image(960, 1280)
    Xw = np.array([[4.0, 0.7, 0.0], [6.0, -1.0, 0.5]])
    R1, t1 = cam.pose.camera_from_world()
    R2, t2 = rot.pose.camera_from_world()
    uv = cam.project(Xw @ R1.T + t1)
    assert np.allclose(rot.project(Xw @ R2.T + t2), _rotate_pixels(uv, 1280, 960, 90))
    assert rot.pose.height_m == cam.pose.height_m
    assert rot.pose.pitch_deg == pytest.approx(cam.pose.pitch_deg)
    assert rot.pose.roll_deg == pytest.approx(cam.pose.roll_deg - 90.0)
    assert math.isclose(cam.for_image(640, 480).pose.pitch_deg, -20.0)
