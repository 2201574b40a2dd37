"""Synthetic scenes shared by the geometry tests (``tests/test_toolkit_geometry_*.py``)."""
import numpy as np
import pytest


def roped_scenes(seed: int, n: int):
    """Synthetic 640x480 scenes with a well-visible rope: ``(sample, perception)`` with
    ground-truth masks and a depth map 1.7x too far (wrong scale, as a network's would be)."""
    pytest.importorskip("embreex")
    from monodbh.calib import Camera
    from monodbh.models.synthetic import generate_sample
    from monodbh.toolkit.evaluation.ground_truth import perception_from_ground_truth

    for i in range(n):
        s = generate_sample(seed, i, (640, 480))
        m = s["meta"]
        if not m["rope"] or m["rope"]["pixels"] < 60:
            continue
        cam = Camera(np.array(m["K"]), np.array(m["dist"]), (640, 480))
        p = perception_from_ground_truth(s, cam, use_silhouette=False)
        p.depth = p.depth * 1.7
        p.depth_is_metric = False
        yield s, p


def paint_stem(W, H, x0, x1, y_base):
    """(H, W, 3) float32: sky grey above row 300, brown ground below, a bark-coloured stem
    between x0 and x1 (anti-aliased) from the top down to ``y_base``."""
    rgb = np.zeros((H, W, 3), np.float32)
    rgb[:300] = (150, 160, 170)
    rgb[300:] = (120, 95, 60)
    xs = np.arange(W, dtype=np.float64)
    cover = np.clip(np.minimum(xs - x0, x1 - xs) + 0.5, 0, 1)[None, :, None]
    stem = np.zeros((H, 1, 1))
    stem[:y_base] = 1.0
    return rgb * (1 - cover * stem) + np.array([70.0, 60.0, 55.0]) * cover * stem


def level_scene(bush: bool):
    """A level pinhole camera 1.5 m above flat ground (f 500 px, horizon at row 300) looking at
    a 0.3 m stem 5 m away: rope (1.3 m) at row 320, base at row 450; the bush hides the stem
    below 0.4 m (row 410)."""
    from monodbh.calib import Camera
    f, cx, cy, Z = 500.0, 240.0, 300.0, 5.0
    W, H = 480, 640
    x0, x1 = cx - 0.5 * f * 0.3 / Z, cx + 0.5 * f * 0.3 / Z
    rgb = paint_stem(W, H, x0, x1, 450)
    yy, xx = np.mgrid[0:H, 0:W]
    tree = np.zeros((H, W), bool)
    tree[:450, int(x0) + 2:int(x1) - 1] = True
    if bush:
        m = ((xx - cx) / 60.0) ** 2 + ((yy - 455) / 45.0) ** 2 < 1
        rgb[m] = (40, 110, 35)
        tree &= ~m
    rgb = np.clip(rgb + np.random.default_rng(0).normal(0, 2.0, rgb.shape), 0, 255).astype(np.uint8)
    ground = (yy >= 300) & ~tree
    if bush:
        ground &= ~m
    rgb[318:322, int(x0):int(x1) + 1] = (200, 30, 30)            # the rope
    depth = np.where(tree, 1.7 * Z, 0.0).astype(np.float32)       # a network 70 % too far
    # (and no depth on the ground: no ground plane, the camera is taken as level)
    cam = Camera(np.array([[f, 0, cx], [0, f, cy], [0, 0, 1]]), None, (W, H))
    return rgb, tree, ground, depth, cam


def roped_pair(rope_to: float, shade_from: float | None = None, W=480, H=400):
    """Grey background, the roped stem (x 200..260, brown bark) and a lighter neighbouring trunk
    behind it (x 260..330); a red rope (rows 198..202) painted from x 200 to ``rope_to``; with
    ``shade_from``, the roped stem (and its rope) darker from there on. Returns rgb (H, W, 3)
    uint8 and the coarse mask the segmenter gives for both trunks together."""
    rng = np.random.default_rng(1)
    rgb = np.zeros((H, W, 3), np.float32)
    rgb[:] = (150, 160, 170)
    rgb[:, 260:330] = (175, 165, 140)
    rgb[:, 200:260] = (90, 70, 55)
    rgb[198:203, 200:int(rope_to)] = (170, 30, 25)
    if shade_from is not None:
        rgb[:, int(shade_from):260] *= 0.55
    rgb = np.clip(rgb + rng.normal(0, 2.0, rgb.shape), 0, 255).astype(np.uint8)
    mask = np.zeros((H, W), bool)
    mask[:, 198:332] = True
    return rgb, mask


def arced_rope_scene(x0=100, x1=380, depth=40.0, found=0.7, W=520, H=420):
    """A wide stem (x ``x0..x1``, brown bark, its mask exact) on a grey background, its red rope
    seen from above: an arc through row 200 at the middle whose ends rise ``depth`` px at the
    silhouette (the front half of an ellipse). The rope finder found the middle ``found`` of it:
    the rope band and the centre line (one point per 10 px) end there. Returns
    ``(rgb (H, W, 3) uint8, mask (H, W) bool, Perception)``."""
    from monodbh.toolkit.geometry import Perception
    rng = np.random.default_rng(2)
    rgb = np.zeros((H, W, 3), np.float32)
    rgb[:] = (150, 160, 170)
    rgb[:, x0:x1] = (90, 70, 55)
    xc, a = 0.5 * (x0 + x1), 0.5 * (x1 - x0)
    xs = np.arange(x0, x1) + 0.5
    ys = 200 - depth * (1 - np.sqrt(np.clip(1 - ((xs - xc) / a) ** 2, 0, 1)))
    for x, y in zip(range(x0, x1), np.round(ys).astype(int)):
        rgb[y - 2:y + 3, x] = (170, 30, 25)
    rgb = np.clip(rgb + rng.normal(0, 2.0, rgb.shape), 0, 255).astype(np.uint8)
    mask = np.zeros((H, W), bool)
    mask[:, x0:x1] = True
    bx0, bx1 = xc - found * a, xc + found * a
    on = (xs >= bx0) & (xs <= bx1)
    L = bx1 - bx0
    band = np.zeros((H, W), bool)
    band[int(200 - L):int(200 + L) + 1, int(bx0):int(bx1)] = True
    perc = Perception(rgb=rgb, camera=None, rope_xy=np.array([xc, 200.0]), rope_dir=np.array([1.0, 0.0]),
                      rope_half_px=2.5, tree_mask=mask, ground_mask=np.zeros_like(mask), edge_search_px=6.0,
                      rope_band_mask=band, rope_length_px=float(L), rope_polyline=np.c_[xs[on], ys[on]][::10])
    return rgb, mask, perc


def knotted_rope_scene(W=480, H=400):
    """The roped stem (x 200..260, brown bark) alone on a grey background, its red rope (rows
    198..202) knotted on the right flank: the knot (rows 194..207) sticks out to x 268 and a
    loose end 4 px thick hangs from it straight down beside the stem (x 262..266, to row 300). The
    coarse mask takes in the knot and the hanging end, as the segmenter's may. Returns
    ``(rgb (H, W, 3) uint8, mask (H, W) bool, Perception)``."""
    rng = np.random.default_rng(3)
    rgb = np.zeros((H, W, 3), np.float32)
    rgb[:] = (150, 160, 170)
    rgb[:, 200:260] = (90, 70, 55)
    red = (170, 30, 25)
    rgb[198:203, 200:260] = red
    rgb[194:208, 256:268] = red
    rgb[207:301, 262:266] = red
    rgb = np.clip(rgb + rng.normal(0, 2.0, rgb.shape), 0, 255).astype(np.uint8)
    mask = np.zeros((H, W), bool)
    mask[:, 199:261] = True
    mask[194:208, 256:268] = True
    mask[207:301, 256:266] = True
    perc = rope_perception(rgb, mask, 201, 266)
    return rgb, mask, perc


def rope_perception(rgb, mask, band_x0, band_x1):
    from monodbh.toolkit.geometry import Perception
    band = np.zeros(mask.shape, bool)
    L = band_x1 - band_x0
    band[200 - L:200 + L + 1, band_x0:band_x1] = True      # as the pipeline's: the rope's length above and below
    return Perception(rgb=rgb, camera=None, rope_xy=np.array([0.5 * (band_x0 + band_x1), 200.0]),
                      rope_dir=np.array([1.0, 0.0]), rope_half_px=2.5, tree_mask=mask,
                      ground_mask=np.zeros_like(mask), edge_search_px=6.0, rope_band_mask=band,
                      rope_length_px=float(band_x1 - band_x0))
