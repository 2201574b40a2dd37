"""Point clouds of a measured photo: the coarse scene cloud and the roped tree's refined cloud.

Lives here: unprojection of depth maps with kornia (the only torch use on the measuring path,
for ``dbh reconstruct`` and overlays) and the clouds built from the measured tree. Imported by
:mod:`monodbh.toolkit.pipeline`.
"""
from __future__ import annotations

import numpy as np

from .result import PointCloud

__all__ = ["unproject_depth", "scene_cloud", "tree_cloud"]


def unproject_depth(depth: np.ndarray, K: np.ndarray, step: int = 1) -> np.ndarray:
    """Camera-frame points ``(H', W', 3)`` from a z-depth map with kornia.

    Parameters
    ----------
    depth : (H, W) float32 metres.
    K : (3, 3) pinhole intrinsics of the depth map.
    step : keep every ``step``-th pixel in each direction (intrinsics adjusted).
    """
    import torch
    from kornia.geometry.depth import depth_to_3d_v2
    d = depth[::step, ::step]
    Ks = K.astype(np.float64).copy()
    Ks[:2] /= step          # pixel i of the subsampled map is pixel i * step of the original
    with torch.inference_mode():
        pts = depth_to_3d_v2(torch.from_numpy(np.ascontiguousarray(d, np.float32))[None],
                             torch.from_numpy(Ks.astype(np.float32))[None])
    return pts[0].numpy()


def scene_cloud(img, depth, K, instance, tid, step: int = 4, max_depth_m: float = 60.0,
                trunk=None) -> PointCloud:
    """The scene's coarse cloud from the (rescaled) depth map, without the measured tree ``tid``
    (it gets its refined cloud).

    Parameters
    ----------
    img : (H, W, 3) uint8; depth : (H, W) float32 metres; K : (3, 3) intrinsics.
    instance : (H, W) tree instance ids; tid : the measured tree's id.
    step : pixel subsampling; max_depth_m : farther points are dropped.
    trunk : (H, W) bool, optional
        Trunk pixels (the trunk network's, else the segmenter's trunk head's): the points' ``trunk`` flag.
    """
    pts = unproject_depth(depth, K, step)
    col = img[::step, ::step]
    ids = instance[::step, ::step].astype(np.int32)
    ok = (depth[::step, ::step] > 0) & (depth[::step, ::step] < max_depth_m)
    ok &= ids != tid
    tr = None if trunk is None else np.asarray(trunk, bool)[::step, ::step][ok]
    return PointCloud(pts[ok].astype(np.float32), col[ok].astype(np.uint8), ids[ok], tr)


def tree_cloud(img, cam, z1, z2, tree_mask, tid, trunk=None) -> PointCloud:
    """The measured tree's front and back surface points (the tree network's metric z1, z2).

    Parameters
    ----------
    img : (H, W, 3) uint8; cam : the image's camera.
    z1, z2 : (H, W) float32 front / back surface depth (0 outside the tree's crop).
    tree_mask : (H, W) bool; tid : the tree's id.
    trunk : (H, W) bool, optional
        Trunk pixels (the trunk network's, else the segmenter's trunk head's): the points' ``trunk`` flag.
    """
    ys, xs = np.nonzero(tree_mask & (z1 > 0))
    if len(xs) == 0:
        return PointCloud.concat([])
    nxy = cam.undistort_points(np.c_[xs, ys].astype(np.float64), normalized=True)
    f = np.c_[nxy * z1[ys, xs, None], z1[ys, xs]]
    b = np.c_[nxy * z2[ys, xs, None], z2[ys, xs]]
    col = img[ys, xs]
    back_col = (col * 0.6).astype(np.uint8)
    tr = None if trunk is None else np.tile(np.asarray(trunk, bool)[ys, xs], 2)
    return PointCloud(np.concatenate([f, b]).astype(np.float32), np.concatenate([col, back_col]),
                      np.full(2 * len(xs), tid, np.int32), tr)
