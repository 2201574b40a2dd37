"""The ground plane fitted to the depth map's ground points (toolkit.geometry.ground)."""
from types import SimpleNamespace

import numpy as np
import pytest

from monodbh.toolkit.geometry.ground import ground_plane


def _level_ground(h=1.5, f=500.0, W=480, H=640, cy=300.0):
    """The depth map of flat ground seen by a level pinhole camera ``h`` m above it."""
    from monodbh.calib import Camera
    v = np.arange(H, dtype=np.float64)[:, None] * np.ones((1, W))
    ground = v > cy + 5
    depth = np.where(ground, h * f / np.maximum(v - cy, 1e-6), 0.0).astype(np.float32)
    cam = Camera(np.array([[f, 0, W / 2], [0, f, cy], [0, 0, 1]]), None, (W, H))
    return SimpleNamespace(depth=depth, ground_mask=ground, tree_mask=np.zeros_like(ground),
                           rope_xy=np.array([W / 2, 320.0]), camera=cam)


def test_level_ground_gives_up_and_the_camera_height():
    perc = _level_ground()
    edges = SimpleNamespace(width_px=20.0)
    pl, why = ground_plane(perc, edges, None)
    assert why == "" and abs(pl.n @ np.array([0.0, -1.0, 0.0]) - 1) < 1e-3
    assert pl.c == pytest.approx(1.5, rel=0.01)
    # a plane far from the pose's (or vanishing point's) up is refused
    pl, why = ground_plane(perc, edges, np.array([1.0, 0.0, 0.0]))
    assert pl is None and why == "ground plane not level"
    perc.ground_mask = np.zeros_like(perc.ground_mask)
    assert ground_plane(perc, edges, None) == (None, "too few ground pixels")
