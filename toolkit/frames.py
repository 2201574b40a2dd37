"""Image frames of the measuring path: the photo, the working image, full-resolution crops.

Lives here: the mapping between the photo's own pixels (distorted, full size) and the working
image's (downscaled to the working long side, undistorted, a pinhole camera), the intrinsics
rescaling both use, and undistorted crops of the full-resolution photo. Imported by
:mod:`monodbh.toolkit.pipeline`; imports ``monodbh.calib`` only.

Pixel convention: integer coordinates are pixel centres, so a pixel ``x`` of an image scaled by
``s`` lands at ``(x + 0.5) * s - 0.5``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["WorkFrame", "work_frame", "rescale_intrinsics", "read_photo", "square_crop", "MIN_PHOTO_SIDE_PX"]

#: the shortest side of a photo the measuring path accepts (pixels): below it no trunk, rope or
#: ground is resolved, and the camera's adaptation to the photo degenerates
#: (``docs/decisions/photo-limits.md``)
MIN_PHOTO_SIDE_PX = 64


def read_photo(path) -> np.ndarray:
    """The ``(H, W, 3)`` uint8 RGB photo at ``path`` as the measuring path reads it: upright
    (EXIF), refused with a one-line :class:`~monodbh.calib.errors.PhotoError` when it is not a
    photo, is corrupt, too large to decode or under :data:`MIN_PHOTO_SIDE_PX` a side."""
    from ..calib import load_photo

    return load_photo(path, min_side_px=MIN_PHOTO_SIDE_PX)


def square_crop(center_xy, frac: float, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)``: a square of side ``frac`` x the long side of an image of ``shape``
    (H, W), centred on ``center_xy`` (rounded to pixels) and shifted to lie inside the image (cut
    to it where larger).

    Examples
    --------
    >>> square_crop((10.0, 50.0), 0.4, (100, 60))
    (0, 30, 40, 70)
    """
    H, W = shape
    side = int(round(frac * max(H, W)))
    cx, cy = int(round(float(center_xy[0]))), int(round(float(center_xy[1])))
    x0 = max(0, min(W - min(side, W), cx - side // 2))
    y0 = max(0, min(H - min(side, H), cy - side // 2))
    return x0, y0, min(W, x0 + side), min(H, y0 + side)


def rescale_intrinsics(K: np.ndarray, sx: float, sy: float, *, inverse: bool = False) -> np.ndarray:
    """The intrinsics ``(3, 3)`` of the same camera on an image scaled by ``(sx, sy)`` per axis.

    Parameters
    ----------
    K : (3, 3) intrinsics of the original image.
    sx, sy : scale of the new image per axis (new size / original size).
    inverse : map back instead (``K`` belongs to the scaled image; divides by the scale, so a
        round trip is exact where the forward map was).

    Returns
    -------
    (3, 3) float64 copy.

    Examples
    --------
    >>> K = np.array([[1000.0, 0, 1999.5], [0, 1000.0, 1499.5], [0, 0, 1]])
    >>> rescale_intrinsics(K, 0.4, 0.4)[0].tolist()
    [400.0, 0.0, 799.5]
    """
    K = np.asarray(K, np.float64).copy()
    if inverse:
        K[0, 0] /= sx
        K[0, 2] = (K[0, 2] + 0.5) / sx - 0.5
        K[1, 1] /= sy
        K[1, 2] = (K[1, 2] + 0.5) / sy - 0.5
    else:
        K[0, 0] *= sx
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 1] *= sy
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K


@dataclass
class WorkFrame:
    """The working image of one photo and how its pixels map to the photo's.

    Attributes
    ----------
    image : (h, w, 3) uint8 working image (downscaled, undistorted).
    camera : pinhole :class:`~monodbh.calib.Camera` of ``image``.
    scale : (sx, sy) working / photo size per axis.
    camera_distorted : the photo's camera at the working size, with its distortion (``camera``
        itself when the lens has none).
    """
    image: np.ndarray
    camera: object
    scale: tuple[float, float]
    camera_distorted: object

    @property
    def shape(self) -> tuple[int, int]:
        """(h, w) of the working image."""
        return self.image.shape[:2]

    def _distorted(self) -> bool:
        return (self.camera_distorted is not self.camera
                and bool(np.any(np.asarray(self.camera_distorted.dist) != 0)))

    def to_work(self, xy) -> np.ndarray:
        """A photo pixel ``(x, y)`` -> the working image's pixel ``(2,)`` (through the lens distortion)."""
        sx, sy = self.scale
        p = np.array([[(xy[0] + 0.5) * sx - 0.5, (xy[1] + 0.5) * sy - 0.5]], np.float64)
        if not self._distorted():
            return p[0]
        return self.camera_distorted.undistort_points(p, K_new=self.camera.K)[0]

    def to_photo(self, xy) -> np.ndarray:
        """A working-image pixel ``(x, y)`` -> the photo's own pixel ``(2,)``; the inverse of
        :meth:`to_work`, so a reported point (the rope's centre, a refused band) tapped again
        with ``--pick`` lands on the same place."""
        sx, sy = self.scale
        p = np.asarray(xy, np.float64)
        if self._distorted():
            n = self.camera.undistort_points(p[None], normalized=True)[0]       # a pinhole camera
            p = self.camera_distorted.project(np.array([[n[0], n[1], 1.0]]))[0]
        return np.array([(p[0] + 0.5) / sx - 0.5, (p[1] + 0.5) / sy - 0.5])

    def full_res_crop(self, rgb: np.ndarray, photo_camera, box) -> np.ndarray:
        """The undistorted full-resolution photo inside ``box`` = (x0, y0, x1, y1) (integers),
        given in the full-resolution pinhole frame of :attr:`camera` (its ``K`` scaled back up).

        Parameters
        ----------
        rgb : (H, W, 3) uint8 photo.
        photo_camera : the photo's :class:`~monodbh.calib.Camera` (any size; adapted here).
        box : crop in full-resolution pinhole pixels (may extend past the photo: zeros there).

        Returns
        -------
        (y1 - y0, x1 - x0, 3) uint8.
        """
        import cv2

        sx, sy = self.scale
        K = rescale_intrinsics(self.camera.K, sx, sy, inverse=True)
        H, W = rgb.shape[:2]
        x0, y0, x1, y1 = box
        cam = photo_camera.for_image(W, H)
        if not np.any(np.asarray(cam.dist) != 0) and np.allclose(K, cam.K):
            xa, ya, xb, yb = max(x0, 0), max(y0, 0), min(x1, W), min(y1, H)
            out = np.zeros((y1 - y0, x1 - x0, 3), np.uint8)
            out[ya - y0:yb - y0, xa - x0:xb - x0] = rgb[ya:yb, xa:xb]
            return out
        u, v = np.meshgrid(np.arange(x0, x1, dtype=np.float64), np.arange(y0, y1, dtype=np.float64))
        rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
        src, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), np.asarray(cam.K, np.float64),
                                   np.asarray(cam.dist, np.float64))
        src = src.reshape(y1 - y0, x1 - x0, 2).astype(np.float32)
        return cv2.remap(rgb, src[..., 0], src[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def work_frame(rgb: np.ndarray, camera, long_side_px: int) -> WorkFrame:
    """Downscale a photo to ``long_side_px`` (never up) and undistort it.

    Parameters
    ----------
    rgb : (H, W, 3) uint8 photo.
    camera : its :class:`~monodbh.calib.Camera` (any size with the same aspect; adapted here).
    long_side_px : the working image's long side.

    Returns
    -------
    :class:`WorkFrame`.
    """
    import cv2

    from ..calib import Camera
    H, W = rgb.shape[:2]
    s = min(1.0, long_side_px / max(W, H))
    w, h = int(round(W * s)), int(round(H * s))
    img = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA) if s < 1 else rgb
    cam = camera.for_image(W, H)
    sx, sy = w / W, h / H
    cw = Camera(rescale_intrinsics(cam.K, sx, sy), cam.dist, (w, h), pose=cam.pose)
    if np.any(np.asarray(cam.dist) != 0):
        und, K_new = cw.undistort_image(img, alpha=0.0)
        pin = Camera(K_new, np.zeros(5), (w, h), pose=cam.pose)
        return WorkFrame(und, pin, (sx, sy), cw)
    return WorkFrame(img, cw, (sx, sy), cw)
