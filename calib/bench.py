"""Timing of ``dbh calibrate`` on synthetic 12 MP board photos (not part of the test suite).

Usage::

    python -m monodbh.calib.bench [--n 20] [--size 4000x3000] [--keep DIR] [--threads N]

Renders ``n`` JPEG photos of a 9x6 chessboard (25 mm squares) through a known camera with
radial distortion, runs ``dbh calibrate`` on them in a subprocess and prints the wall time and
the recovered intrinsics next to the true ones.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

__all__ = ["render_distorted_board", "main"]


def _inverse_distortion_map(K: np.ndarray, dist: np.ndarray, size: tuple[int, int],
                            step: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """For every distorted pixel, the ideal (undistorted) pixel position, float32 maps (H, W).

    Solved with ``cv2.undistortPoints`` on a grid every ``step`` pixels and interpolated
    (the field is smooth), which keeps 12 MP maps cheap.
    """
    import cv2

    w, h = size
    gx = np.arange(0, w + step, step, dtype=np.float64)
    gy = np.arange(0, h + step, step, dtype=np.float64)
    X, Y = np.meshgrid(gx, gy)
    pts = np.stack([X.ravel(), Y.ravel()], -1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
    und = cv2.undistortPoints(pts, K, dist, None, None, K, crit).reshape(len(gy), len(gx), 2)
    # Bilinear interpolation of the coarse grid: grid node (i, j) sits at pixel (i, j) * step.
    xs = np.broadcast_to((np.arange(w, dtype=np.float32) / step)[None, :], (h, w))
    ys = np.broadcast_to((np.arange(h, dtype=np.float32) / step)[:, None], (h, w))
    xs, ys = np.ascontiguousarray(xs), np.ascontiguousarray(ys)
    map_x = cv2.remap(und[..., 0].astype(np.float32), xs, ys, cv2.INTER_LINEAR)
    map_y = cv2.remap(und[..., 1].astype(np.float32), xs, ys, cv2.INTER_LINEAR)
    return np.ascontiguousarray(map_x), np.ascontiguousarray(map_y)


def render_distorted_board(K: np.ndarray, maps: tuple[np.ndarray, np.ndarray],
                           size: tuple[int, int], pattern: tuple[int, int], square: float,
                           rvec: np.ndarray, tvec: np.ndarray, *, px_per_square: int = 64,
                           rng: np.random.Generator | None = None) -> np.ndarray:
    """Render a chessboard photo ``(H, W)`` uint8 through ``K`` and the distortion ``maps``.

    The ideal image is a homography of a texture (``cv2.warpPerspective``); the distortion is
    applied with ``cv2.remap`` through the inverse distortion maps.
    """
    import cv2

    cols, rows = pattern
    n = px_per_square
    margin = n  # one white square around the board
    tex = np.full(((rows + 1) * n + 2 * margin, (cols + 1) * n + 2 * margin), 235, np.uint8)
    for j in range(rows + 1):
        for i in range(cols + 1):
            if (i + j) % 2 == 0:
                y0, x0 = margin + j * n, margin + i * n
                tex[y0:y0 + n, x0:x0 + n] = 20
    # Texture pixel (u, v) centre -> board metres: inner corner (0, 0) is at u = margin + n - 0.5.
    s = square / n
    T = np.array([[s, 0, -(margin + n - 0.5) * s], [0, s, -(margin + n - 0.5) * s], [0, 0, 1]])
    R = cv2.Rodrigues(np.asarray(rvec, np.float64))[0]
    H = K @ np.column_stack([R[:, 0], R[:, 1], np.asarray(tvec, np.float64)]) @ T
    ideal = cv2.warpPerspective(tex, H, size, flags=cv2.INTER_AREA, borderValue=110)
    img = cv2.remap(ideal, maps[0], maps[1], cv2.INTER_LINEAR, borderValue=110)
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    if rng is not None:
        img = np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)
    return img


def main(argv: list[str] | None = None) -> int:
    import cv2

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20)
    ap.add_argument("--size", default="4000x3000")
    ap.add_argument("--keep", type=Path, default=None, help="keep the photos here")
    ap.add_argument("--threads", type=int, default=None)
    a = ap.parse_args(argv)
    w, h = (int(v) for v in a.size.lower().split("x"))
    f = 0.75 * w
    K = np.array([[f, 0, w / 2 - 0.5 + 13.0], [0, f, h / 2 - 0.5 - 9.0], [0, 0, 1]])
    dist = np.array([0.12, -0.25, 0.0, 0.0, 0.1])
    pattern, square = (9, 6), 0.025
    rng = np.random.default_rng(0)
    out = a.keep or Path(tempfile.mkdtemp(prefix="dbh_bench_"))
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    maps = _inverse_distortion_map(K, dist, (w, h))
    files = []
    board_w, board_h = (pattern[0] - 1) * square, (pattern[1] - 1) * square
    for i in range(a.n):
        z = rng.uniform(0.3, 0.55)
        rvec = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3)])
        # Board centre somewhere in the frame.
        cx = rng.uniform(-0.28, 0.28) * z * w / f
        cy = rng.uniform(-0.25, 0.25) * z * h / f
        R = cv2.Rodrigues(rvec)[0]
        tvec = np.array([cx, cy, z]) - R @ np.array([board_w / 2, board_h / 2, 0.0])
        img = render_distorted_board(K, maps, (w, h), pattern, square, rvec, tvec, rng=rng)
        p = out / f"board_{i:02d}.jpg"
        cv2.imwrite(str(p), img, [cv2.IMWRITE_JPEG_QUALITY, 92])
        files.append(str(p))
    print(f"rendered {a.n} photos {w}x{h} in {time.perf_counter() - t0:.1f} s -> {out}")
    cmd = [sys.executable, "-c", "from monodbh.cli.main import main; main()", "calibrate", *files, "--board", "9x6",
           "--square", str(square), "-o", str(out / "cam.yaml"), "--json"]
    if a.threads:
        cmd += ["--threads", str(a.threads)]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    sys.stderr.write(r.stderr)
    if r.returncode:
        print(f"dbh calibrate failed with status {r.returncode}")
        return 1
    import json

    d = json.loads(r.stdout)
    print(f"dbh calibrate on {a.n} photos of {w * h / 1e6:.0f} MP: {dt:.2f} s wall "
          f"(detect {d['timings_s']['detect']:.2f} s, calibrate {d['timings_s']['calibrate']:.2f} s)")
    print(f"true fx {K[0, 0]:.2f} cx {K[0, 2]:.2f} cy {K[1, 2]:.2f}; got fx {d['fx']:.2f} "
          f"({100 * (d['fx'] / K[0, 0] - 1):+.3f} %) cx {d['cx']:.2f} cy {d['cy']:.2f}, "
          f"rms {d['rms_px']:.3f} px, {d['views_used']} views used")
    return 0


if __name__ == "__main__":
    sys.exit(main())
