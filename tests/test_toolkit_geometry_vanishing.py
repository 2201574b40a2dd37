"""Vertical vanishing direction from near-vertical lines (toolkit.geometry.vanishing)."""
import cv2
import numpy as np

from monodbh.calib.camera import CameraPose
from monodbh.toolkit.geometry import VanishingConfig, vertical_direction


def _rot(pitch_deg, roll_deg):
    """R_cam_from_world of a camera with this pitch and roll (calib.CameraPose conventions)."""
    return np.asarray(CameraPose.from_angles(1.5, pitch_deg, roll_deg).R_world_from_camera).T


def _trunks_photo(R, K, W=800, H=600, seed=0, lean_deg=0.0):
    """Grey photo of vertical (optionally leaning) trunks, projected through R, K."""
    rng = np.random.default_rng(seed)
    img = np.full((H, W), 70, np.uint8)
    for _ in range(14):
        y, x = rng.uniform(-6, 6), rng.uniform(4, 14)      # the level camera looks along world +x
        r = rng.uniform(0.1, 0.3)
        lean = np.radians(rng.normal(0, lean_deg)) if lean_deg else 0.0
        az = rng.uniform(0, 2 * np.pi)
        axis = np.array([np.sin(lean) * np.cos(az), np.sin(lean) * np.sin(az), np.cos(lean)])
        poly = []
        for side in (-1, 1):
            for z in np.linspace(-1.5, 6.0, 20)[:: side]:
                P = np.array([x, y + side * r, 0.0]) + (z + 1.5) * axis + np.array([0, 0, -1.5])
                pc = R @ P                     # camera at the world origin
                if pc[2] <= 0.1:
                    continue
                uv = K @ (pc / pc[2])
                poly.append(uv[:2])
        if len(poly) > 4:
            cv2.fillPoly(img, [np.round(np.array(poly)).astype(np.int32)], int(rng.integers(140, 230)))
    return cv2.GaussianBlur(img, (3, 3), 0.8)


def _angle(a, b):
    return np.degrees(np.arccos(np.clip(abs(a @ b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


def test_recovers_pitch_and_roll_of_vertical_trunks():
    K = np.array([[600.0, 0, 399.5], [0, 600.0, 299.5], [0, 0, 1]])
    for pitch, roll in ((0, 0), (12, 4), (-10, -5)):
        R = _rot(pitch, roll)
        est = vertical_direction(_trunks_photo(R, K), K)
        assert est, est.reason
        up_true = R @ np.array([0, 0, 1.0])
        assert _angle(est.up, up_true) < 0.5, (pitch, roll, _angle(est.up, up_true))
        p, r = est.pitch_roll_deg
        assert abs(p - pitch) < 0.6 and abs(r - roll) < 0.6, (pitch, roll, p, r)
        assert est.up[1] < 0


def test_leaning_trunks_give_an_honest_sigma():
    K = np.array([[600.0, 0, 399.5], [0, 600.0, 299.5], [0, 0, 1]])
    errs, sig = [], []
    for seed in range(6):
        R = _rot(8, 2)
        est = vertical_direction(_trunks_photo(R, K, seed=seed, lean_deg=3.0), K)
        assert est
        errs.append(_angle(est.up, R @ np.array([0, 0, 1.0])))
        sig.append(est.sigma_deg)
    assert np.median(errs) < 2.5
    assert np.mean(np.array(errs) <= 2 * np.array(sig)) >= 0.8


def test_no_lines_is_falsy_with_reason():
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    flat = np.full((480, 640), 128, np.uint8)
    est = vertical_direction(flat, K)
    assert not est and "too few" in est.reason
    # only horizontal lines: nothing near vertical
    img = flat.copy()
    for y in range(40, 440, 60):
        img[y:y + 20] = 220
    assert not vertical_direction(img, K)


def test_the_fewest_stems_come_from_the_config():
    K = np.array([[600.0, 0, 399.5], [0, 600.0, 299.5], [0, 0, 1]])
    img = _trunks_photo(_rot(5, 2), K)
    est = vertical_direction(img, K)
    assert est and est.n_groups < 40
    est = vertical_direction(img, K, config=VanishingConfig(min_groups=40))
    assert not est and "too few" in est.reason
