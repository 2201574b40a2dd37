"""Synthetic boards rendered here through a known camera with radial distortion.

Rendering: every output pixel is supersampled (2 x 2); each sample is undistorted with the
true camera (``cv2.undistortPoints``, i.e. distortion applied through an inverse map, as a
remap would) and intersected with the board plane through the board homography; the board
texture is evaluated there and the samples are averaged (``INTER_AREA``).
"""
import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from monodbh.calib import Board, Camera, calibrate, load_camera, save_camera
from monodbh.calib.marker import read_marker_width_m, write_marker_width
from monodbh.cli.main import app

SIZE = (640, 480)
K_TRUE = np.array([[600.0, 0.0, 327.4], [0.0, 600.0, 236.1], [0.0, 0.0, 1.0]])
DIST_TRUE = np.array([-0.28, 0.09, 0.0, 0.0, 0.0])
BACKGROUND = 100.0


def _sample_grid(K, dist, size, ss):
    """Normalized undistorted coordinates of the ss x ss subpixel centres, (h*ss, w*ss, 2)."""
    w, h = size
    xs = (np.arange(w * ss) + 0.5) / ss - 0.5
    ys = (np.arange(h * ss) + 0.5) / ss - 0.5
    X, Y = np.meshgrid(xs, ys)
    pts = np.stack([X.ravel(), Y.ravel()], -1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 60, 1e-12)
    n = cv2.undistortPoints(pts, K, dist, None, None, None, crit)
    return n.reshape(h * ss, w * ss, 2).astype(np.float32)


def _render(grid, size, rvec, tvec, texture, rng, noise=1.5):
    """Gray uint8 image of a planar texture ``texture(bx, by) -> float`` at pose (rvec, tvec)."""
    R = cv2.Rodrigues(np.asarray(rvec, np.float64))[0]
    Hi = np.linalg.inv(np.column_stack([R[:, 0], R[:, 1], np.asarray(tvec, np.float64)]))
    Hi = Hi.astype(np.float32)
    gx, gy = grid[..., 0], grid[..., 1]
    hz = Hi[2, 0] * gx + Hi[2, 1] * gy + Hi[2, 2]
    bx = (Hi[0, 0] * gx + Hi[0, 1] * gy + Hi[0, 2]) / hz
    by = (Hi[1, 0] * gx + Hi[1, 1] * gy + Hi[1, 2]) / hz
    val = np.where(hz > 0, texture(bx, by), np.float32(BACKGROUND)).astype(np.float32)
    img = cv2.resize(val, size, interpolation=cv2.INTER_AREA)
    img = cv2.GaussianBlur(img, (0, 0), 0.6)
    img = img + rng.normal(0.0, noise, img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _chessboard_texture(cols, rows, square):
    """Anti-aliased chessboard: each edge is a linear ramp one sample wide (a box filter)."""
    inv = np.float32(1.0 / square)

    def soft(u, width):
        t = u * inv
        k = np.floor(t)
        f = t - k
        sign = np.float32(1.0) - np.float32(2.0) * (k - np.float32(2.0) * np.floor(k * 0.5))
        d = np.minimum(f, np.float32(1.0) - f) * sign  # signed distance to a line, squares
        return np.clip(d * (np.float32(2.0) / np.maximum(width * inv, np.float32(1e-6))), -1, 1)

    def tex(bx, by):
        wx = np.hypot(*np.gradient(bx))  # board length covered by one sample
        wy = np.hypot(*np.gradient(by))
        i = np.floor(bx * (1.0 / square)).astype(np.int32) + 1  # inner corner (0, 0) at origin
        j = np.floor(by * (1.0 / square)).astype(np.int32) + 1
        # Checker value in [-1, 1]; -1 (black) on the square with i + j even next to (0, 0).
        checker = -soft(bx, wx) * soft(by, wy)
        board = (i >= 0) & (i <= cols) & (j >= 0) & (j <= rows)
        white, black = 235.0, 25.0
        val = np.float32(0.5 * (white + black)) + np.float32(0.5 * (white - black)) * checker
        margin = (i >= -1) & (i <= cols + 1) & (j >= -1) & (j <= rows + 1)
        return np.where(board, val, np.where(margin, white, BACKGROUND)).astype(np.float32)
    return tex


def _charuco_texture(board, px=48):
    img = board.cv_board().generateImage((board.cols * px, board.rows * px), marginSize=0)
    img = img.astype(np.float32) * (210.0 / 255.0) + 25.0
    sq = board.square_m

    def tex(bx, by):
        u = (bx * (px / sq) - 0.5).astype(np.float32)
        v = (by * (px / sq) - 0.5).astype(np.float32)
        out = cv2.remap(img, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                        borderValue=235.0)
        inside = (bx > -sq) & (bx < (board.cols + 1) * sq) & (by > -sq) & (by < (board.rows + 1) * sq)
        return np.where(inside, out, np.float32(BACKGROUND))
    return tex


def _poses(n, extent, rng, K=K_TRUE, size=SIZE, margin=0.06):
    """Board poses (rvec, tvec) with the whole board (+margin) inside the frame."""
    (x0, y0), (x1, y1) = extent
    out = []
    while len(out) < n:
        rvec = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), rng.uniform(-0.4, 0.4)])
        z = rng.uniform(0.45, 0.8)
        centre = np.array([rng.uniform(-0.3, 0.3) * z, rng.uniform(-0.22, 0.22) * z, z])
        R = cv2.Rodrigues(rvec)[0]
        tvec = centre - R @ np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
        corners = np.array([[x0 - margin, y0 - margin, 0], [x1 + margin, y0 - margin, 0],
                            [x1 + margin, y1 + margin, 0], [x0 - margin, y1 + margin, 0]])
        uv, _ = cv2.projectPoints(corners, rvec, tvec, K, DIST_TRUE)
        uv = uv.reshape(-1, 2)
        if (uv.min() > 5 and uv[:, 0].max() < size[0] - 5 and uv[:, 1].max() < size[1] - 5
                and (R @ np.array([0, 0, 1.0]))[2] > 0.45):
            out.append((rvec, tvec))
    return out


@pytest.fixture(scope="module")
def grid():
    return _sample_grid(K_TRUE, DIST_TRUE, SIZE, 2)


@pytest.fixture(scope="module")
def chessboard_views(grid):
    rng = np.random.default_rng(7)
    cols, rows, sq = 9, 6, 0.03
    tex = _chessboard_texture(cols, rows, sq)
    poses = _poses(12, ((0, 0), ((cols - 1) * sq, (rows - 1) * sq)), rng)
    return [_render(grid, SIZE, r, t, tex, rng) for r, t in poses], Board(cols, rows, sq)


def test_synthetic_chessboard_recovers_intrinsics(chessboard_views):
    images, board = chessboard_views
    res = calibrate(images, board)
    K = res.camera.K
    assert len(res.used) >= 10
    assert abs(K[0, 0] / K_TRUE[0, 0] - 1) < 0.003
    assert abs(K[1, 1] / K_TRUE[1, 1] - 1) < 0.003
    assert np.hypot(K[0, 2] - K_TRUE[0, 2], K[1, 2] - K_TRUE[1, 2]) < 2.0
    assert abs(res.camera.dist[0] - DIST_TRUE[0]) < 0.02
    assert res.rms < 0.2
    assert set(res.std) >= {"fx", "fy", "cx", "cy"} and all(v > 0 for v in res.std.values())
    assert [c.name for c in res.coverage] == ["X", "Y", "size", "skew"]
    assert all(0.0 <= c.progress <= 1.0 for c in res.coverage)


def test_synthetic_non_planar_release_object(chessboard_views):
    images, board = chessboard_views
    res = calibrate(images[:5], board, non_planar=True, reject_outliers=False)
    assert abs(res.camera.fx / K_TRUE[0, 0] - 1) < 0.005


def test_outlier_view_is_rejected(chessboard_views):
    images, board = chessboard_views
    from monodbh.calib import calibrate_views, detect_views

    views, size = detect_views(images, board)
    d = views[3].detection
    d.corners = d.corners + np.random.default_rng(1).normal(0, 1.5, d.corners.shape).astype(np.float32)
    res = calibrate_views(views, board, size)
    assert res.views[3].status == "rejected" and "reprojection error" in res.views[3].reason
    assert len(res.used) == len(images) - 1
    assert abs(res.camera.fx / K_TRUE[0, 0] - 1) < 0.003


def test_synthetic_charuco(grid, tmp_path):
    rng = np.random.default_rng(11)
    board = Board(7, 5, 0.04, charuco=True, marker_m=0.03, dictionary="DICT_5X5_100")
    tex = _charuco_texture(board)
    poses = _poses(8, ((0, 0), (7 * 0.04, 5 * 0.04)), rng)
    images = [_render(grid, SIZE, r, t, tex, rng) for r, t in poses]
    res = calibrate(images, board)
    assert len(res.used) >= 6
    assert abs(res.camera.fx / K_TRUE[0, 0] - 1) < 0.01
    assert np.hypot(*(res.camera.K[:2, 2] - K_TRUE[:2, 2])) < 4.0
    # The same through the command line.
    files = []
    for k, im in enumerate(images):
        files.append(str(tmp_path / f"charuco{k}.png"))
        cv2.imwrite(files[-1], im)
    r = CliRunner().invoke(app, ["calibrate", *files, "--charuco", "--board", "7x5", "--square",
                                 "0.04", "--marker", "0.03", "--dict", "DICT_5X5_100", "-o",
                                 str(tmp_path / "cam.yaml")])
    assert r.exit_code == 0, r.stderr
    assert abs(load_camera(tmp_path / "cam.yaml").fx / K_TRUE[0, 0] - 1) < 0.01


@pytest.mark.parametrize("rotate", [False, True], ids=["landscape", "portrait"])
def test_calibrate_pose_from_ground_board(tmp_path, rotate):
    """Board on the ground, camera 1.4 m up, pitched 30 deg down, rolled 2 deg; photo at 2x."""
    from monodbh.calib import CameraPose

    truth = CameraPose.from_angles(1.4, -30.0, 2.0)
    cols, rows, sq = 9, 6, 0.08
    # Board lying on the ground, centred where the optical axis meets it; board x -> world -y.
    R_wb = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    centre = np.array([1.4 / np.tan(np.radians(30.0)), 0.0, 0.0])
    o = centre - R_wb @ np.array([(cols - 1) * sq / 2, (rows - 1) * sq / 2, 0.0])
    R_cw, t_cw = truth.camera_from_world()
    rvec = cv2.Rodrigues(R_cw @ R_wb)[0].ravel()
    tvec = R_cw @ o + t_cw
    big = Camera(K_TRUE, DIST_TRUE, SIZE).for_image(1280, 960)
    grid = _sample_grid(big.K, big.dist, (1280, 960), 1)
    img = _render(grid, (1280, 960), rvec, tvec, _chessboard_texture(cols, rows, sq),
                  np.random.default_rng(3))
    if rotate:
        img = cv2.rotate(img, cv2.ROTATE_90_CLOCKWISE)
    photo = tmp_path / "ground.png"
    cv2.imwrite(str(photo), img)
    cam_path = tmp_path / "cam.yaml"
    save_camera(Camera(K_TRUE, DIST_TRUE, SIZE), cam_path)
    write_marker_width(cam_path, 10)          # the crew's marker, set before the pose
    r = CliRunner().invoke(app, ["calibrate-pose", str(photo), "--calib", str(cam_path),
                                 "--board", f"{cols}x{rows}", "--square", str(sq), "--json"])
    assert r.exit_code == 0, r.stderr
    assert "camera height" in r.stderr
    pose = load_camera(cam_path).pose
    assert pose is not None
    assert read_marker_width_m(cam_path) == pytest.approx(0.010)     # kept through the rewrite
    assert abs(pose.height_m - 1.4) < 0.01
    assert abs(pose.pitch_deg - (-30.0)) < 0.2
    assert abs(pose.roll_deg - 2.0) < 0.2
    assert np.allclose(pose.t_world_from_camera[:2], 0)
    assert abs(pose.yaw_deg) < 1e-6
    # Stored in the calibration (landscape) camera frame whatever the photo's orientation.
    assert np.abs(pose.R_world_from_camera - truth.R_world_from_camera).max() < 0.005
