"""Pinhole camera model with OpenCV distortion, adaptation to a photo, optional ground pose.

Conventions
-----------
Pixels
    OpenCV's pixel-centre convention everywhere: the centre of pixel ``(col, row)`` has the
    coordinates ``(x, y) = (col, row)``; an image of ``W x H`` pixels spans
    ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``. Rescaling an image by ``s`` therefore maps
    ``x -> s * (x + 0.5) - 0.5`` (so ``cx' = s * (cx + 0.5) - 0.5``, ``fx' = s * fx``), and
    rotating it by 90 degrees clockwise maps ``(x, y) -> (H - 1 - y, x)``.
Camera frame
    OpenCV: x right, y down, z forward (optical axis). Distortion coefficients are OpenCV's
    ``(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, tauX, tauY]]]])``.
World frame of a :class:`CameraPose`
    Metres, z up, ground plane ``z = 0``. The pose estimated by ``dbh calibrate-pose`` puts the
    origin on the ground straight below the camera and removes the yaw, so world +x is the
    viewing direction projected on the ground, +y points left and z up (as the synthetic
    generator's ``yaw_deg = 0``): ``t_world_from_camera = (0, 0, height_m)``. A world point is
    ``X_w = R @ X_c + t``.
Angles
    ``pitch_deg`` > 0: the camera looks up (optical axis above the horizon); < 0: looks down.
    ``roll_deg`` > 0: the camera is turned clockwise about its optical axis as seen by the
    photographer behind it (its right side dips, the horizon in the photo rises to the right).
    ``yaw_deg``: heading of the optical axis, 0 along world +x, > 0 toward +y (turning left).
    ``R_world_from_camera = Rz(yaw) @ R0 @ Rx(pitch) @ Rz(roll)`` with ``R0`` the level camera
    looking along +x (camera x -> world -y, camera y -> world -z, camera z -> world +x),
    rotations right-handed about the current camera axes. This matches
    ``monodbh.models.synthetic`` (``_rotation(yaw, pitch, roll)``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Optional, Sequence

import numpy as np

from .errors import CameraFileError

if TYPE_CHECKING:  # pragma: no cover
    from .photo import PathLike

__all__ = ["Camera", "CameraPose", "CalibrationInfo", "DIST_LENGTHS"]

#: Numbers of distortion coefficients OpenCV accepts.
DIST_LENGTHS = (4, 5, 8, 12, 14)

# Level camera looking along world +x: camera x (right) -> world -y, camera y (down) -> -z,
# camera z (forward) -> +x. Columns are the camera axes in world coordinates.
_R0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
# Camera frame of a photo rotated 90 deg clockwise: X' = -Y, Y' = X  (X' = _M90 @ X).
_M90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def _rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=np.float64, copy=True)
    a.setflags(write=False)
    return a


class CameraPose:
    """Rigid transform world-from-camera for a camera above level ground (world z up).

    Parameters
    ----------
    R_world_from_camera : array_like, shape (3, 3)
        Rotation, orthonormal with determinant +1; its columns are the camera axes in world
        coordinates.
    t_world_from_camera : array_like, shape (3,)
        Camera centre in world coordinates (metres). ``t[2]`` is the height above ground.

    Notes
    -----
    See the module docstring for the frames and the sign conventions of the angles.
    """

    __slots__ = ("_R", "_t")

    def __init__(self, R_world_from_camera: Any, t_world_from_camera: Any) -> None:
        R = np.asarray(R_world_from_camera, dtype=np.float64)
        t = np.asarray(t_world_from_camera, dtype=np.float64).reshape(-1)
        if R.shape != (3, 3):
            raise ValueError(f"R_world_from_camera must have shape (3, 3), got {R.shape}")
        if t.shape != (3,):
            raise ValueError(f"t_world_from_camera must have 3 elements, got {t.size}")
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            raise ValueError("camera pose contains NaN or infinity")
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
            raise ValueError("R_world_from_camera is not a rotation (orthonormal, det +1)")
        self._R = _readonly(R)
        self._t = _readonly(t)

    # -- construction -------------------------------------------------------------------
    @classmethod
    def from_angles(cls, height_m: float, pitch_deg: float, roll_deg: float,
                    yaw_deg: float = 0.0) -> "CameraPose":
        """Pose of a camera ``height_m`` above the ground with the given angles (degrees).

        ``R = Rz(yaw) @ R0 @ Rx(pitch) @ Rz(roll)``, ``t = (0, 0, height_m)``.
        """
        R = (_rz(math.radians(yaw_deg)) @ _R0 @ _rx(math.radians(pitch_deg))
             @ _rz(math.radians(roll_deg)))
        return cls(R, [0.0, 0.0, float(height_m)])

    # -- accessors -----------------------------------------------------------------------
    @property
    def R_world_from_camera(self) -> np.ndarray:
        """(3, 3) float64 rotation world-from-camera (read-only)."""
        return self._R

    @property
    def t_world_from_camera(self) -> np.ndarray:
        """(3,) float64 camera centre in world coordinates, metres (read-only)."""
        return self._t

    @property
    def height_m(self) -> float:
        """Height of the camera centre above the ground plane ``z = 0``, metres."""
        return float(self._t[2])

    @property
    def pitch_deg(self) -> float:
        """Elevation of the optical axis above the horizon, degrees (> 0: looks up)."""
        return math.degrees(math.asin(float(np.clip(self._R[2, 2], -1.0, 1.0))))

    @property
    def roll_deg(self) -> float:
        """Rotation about the optical axis, degrees (> 0: clockwise seen from behind)."""
        return math.degrees(math.atan2(-self._R[2, 0], -self._R[2, 1]))

    @property
    def yaw_deg(self) -> float:
        """Heading of the optical axis about world z, degrees (0: along +x, > 0: toward +y)."""
        f = self._R[:, 2]
        if math.hypot(f[0], f[1]) < 1e-9:  # looking straight up/down: use the image "up"
            u = -self._R[:, 1]
            return math.degrees(math.atan2(u[1], u[0]))
        return math.degrees(math.atan2(f[1], f[0]))

    def camera_from_world(self) -> tuple[np.ndarray, np.ndarray]:
        """Inverse transform ``(R_cw (3, 3), t_cw (3,))`` with ``X_c = R_cw @ X_w + t_cw``."""
        Rt = self._R.T
        return Rt.copy(), -Rt @ self._t

    def rotated_photo(self, rotation: int) -> "CameraPose":
        """Pose of the camera frame of a photo rotated ``rotation`` degrees clockwise (0/90/180/270)."""
        M = np.linalg.matrix_power(_M90, (rotation // 90) % 4)
        return CameraPose(self._R @ M.T, self._t)

    def allclose(self, other: "CameraPose", atol: float = 1e-9) -> bool:
        """True when both rotation and translation agree within ``atol``."""
        return bool(np.allclose(self._R, other._R, atol=atol, rtol=0)
                    and np.allclose(self._t, other._t, atol=atol, rtol=0))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraPose):
            return NotImplemented
        return bool(np.array_equal(self._R, other._R) and np.array_equal(self._t, other._t))

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return (f"CameraPose(height_m={self.height_m:.4f}, pitch_deg={self.pitch_deg:.3f}, "
                f"roll_deg={self.roll_deg:.3f})")


@dataclass(eq=False)
class CalibrationInfo:
    """Bookkeeping of a calibration, as OpenCV's calibration sample stores it.

    All fields are optional; they are written to and read from cam.yaml but play no part in
    the camera model. Arrays: ``per_view_reprojection_errors`` (n,) float32,
    ``extrinsic_parameters`` (n, 6) float64 (rvec, tvec per view, metres),
    ``std_deviations_intrinsics`` (18,) float64 in OpenCV's order
    ``fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, tauX, tauY``.
    """

    calibration_time: Optional[str] = None
    nframes: Optional[int] = None
    board_width: Optional[int] = None
    board_height: Optional[int] = None
    square_size: Optional[float] = None
    aspect_ratio: Optional[float] = None
    flags: int = 0
    avg_reprojection_error: Optional[float] = None
    per_view_reprojection_errors: Optional[np.ndarray] = None
    extrinsic_parameters: Optional[np.ndarray] = None
    std_deviations_intrinsics: Optional[np.ndarray] = None

    def __post_init__(self) -> None:
        if self.per_view_reprojection_errors is not None:
            self.per_view_reprojection_errors = np.asarray(
                self.per_view_reprojection_errors, dtype=np.float32).reshape(-1)
        if self.extrinsic_parameters is not None:
            self.extrinsic_parameters = np.asarray(
                self.extrinsic_parameters, dtype=np.float64).reshape(-1, 6)
        if self.std_deviations_intrinsics is not None:
            self.std_deviations_intrinsics = np.asarray(
                self.std_deviations_intrinsics, dtype=np.float64).reshape(-1)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CalibrationInfo):
            return NotImplemented
        for f in self.__dataclass_fields__:
            a, b = getattr(self, f), getattr(other, f)
            if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
                if a is None or b is None or not np.array_equal(a, b):
                    return False
            elif a != b:
                return False
        return True


def _rotate_dist(dist: np.ndarray) -> np.ndarray:
    """Distortion coefficients of a photo rotated 90 degrees clockwise (see `Camera.for_image`)."""
    d = dist.copy()
    n = d.size
    if n >= 4:
        p1, p2 = dist[2], dist[3]
        d[2], d[3] = p2, -p1
    if n >= 12:
        s1, s2, s3, s4 = dist[8:12]
        d[8:12] = (-s3, -s4, s1, s2)
    if n >= 14 and (abs(dist[12]) > 0 or abs(dist[13]) > 0):
        raise CameraFileError("cannot rotate a camera with a tilted sensor model (tauX, tauY != 0)")
    return d


class Camera:
    """Pinhole camera with OpenCV distortion for photos of one size, plus an optional pose.

    Parameters
    ----------
    K : array_like, shape (3, 3)
        Camera matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels.
    dist : array_like, shape (n,), optional
        OpenCV distortion coefficients, ``n`` in (4, 5, 8, 12, 14); zeros(5) when omitted.
    image_size : tuple of int
        ``(width, height)`` of the photos the camera matrix refers to.
    pose : CameraPose, optional
        Camera pose over level ground (see :class:`CameraPose`), ``None`` when unknown.
    name : str, optional
        Camera name (ROS ``camera_name``).
    info : CalibrationInfo, optional
        Calibration bookkeeping kept for the file formats.

    Notes
    -----
    Instances are immutable: arrays are read-only and methods return new cameras. Use
    :meth:`for_image` before measuring a photo whose size or orientation differs from the
    calibration images.
    """

    __slots__ = ("_K", "_dist", "_size", "_pose", "_name", "_info")

    def __init__(self, K: Any, dist: Any = None, image_size: Sequence[int] | None = None, *,
                 pose: Optional[CameraPose] = None, name: str = "camera",
                 info: Optional[CalibrationInfo] = None) -> None:
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must have shape (3, 3), got {K.shape}")
        if not np.all(np.isfinite(K)):
            raise ValueError("K contains NaN or infinity")
        if not (K[0, 0] > 0 and K[1, 1] > 0) or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 \
                or K[2, 2] != 1:
            raise ValueError("K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
        dist = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64).reshape(-1)
        if dist.size not in DIST_LENGTHS:
            raise ValueError(f"dist must have one of {DIST_LENGTHS} elements, got {dist.size}")
        if not np.all(np.isfinite(dist)):
            raise ValueError("dist contains NaN or infinity")
        if image_size is None or len(image_size) != 2:
            raise ValueError("image_size must be (width, height)")
        w, h = (int(v) for v in image_size)
        if w <= 0 or h <= 0 or w != image_size[0] or h != image_size[1]:
            raise ValueError(f"image_size must be two positive integers, got {tuple(image_size)}")
        if pose is not None and not isinstance(pose, CameraPose):
            raise TypeError(f"pose must be a CameraPose or None, got {type(pose).__name__}")
        if info is not None and not isinstance(info, CalibrationInfo):
            raise TypeError(f"info must be a CalibrationInfo or None, got {type(info).__name__}")
        self._K = _readonly(K)
        self._dist = _readonly(dist)
        self._size = (w, h)
        self._pose = pose
        self._name = str(name)
        self._info = info

    # -- basic accessors -------------------------------------------------------------------
    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 camera matrix (read-only)."""
        return self._K

    @property
    def dist(self) -> np.ndarray:
        """(n,) float64 OpenCV distortion coefficients (read-only)."""
        return self._dist

    @property
    def pose(self) -> Optional[CameraPose]:
        """Pose over level ground, or None (measurement then works without it)."""
        return self._pose

    @property
    def name(self) -> str:
        """Camera name (ROS ``camera_name``)."""
        return self._name

    @property
    def info(self) -> Optional[CalibrationInfo]:
        """Calibration bookkeeping (OpenCV file keys), or None."""
        return self._info

    @property
    def image_size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels."""
        return self._size

    @property
    def width(self) -> int:
        return self._size[0]

    @property
    def height(self) -> int:
        return self._size[1]

    @property
    def fx(self) -> float:
        return float(self._K[0, 0])

    @property
    def fy(self) -> float:
        return float(self._K[1, 1])

    @property
    def cx(self) -> float:
        return float(self._K[0, 2])

    @property
    def cy(self) -> float:
        return float(self._K[1, 2])

    def replace(self, **changes: Any) -> "Camera":
        """Copy with some of ``K, dist, image_size, pose, name, info`` replaced."""
        kw = dict(K=self._K, dist=self._dist, image_size=self._size, pose=self.pose,
                  name=self.name, info=self.info)
        unknown = set(changes) - set(kw)
        if unknown:
            raise TypeError(f"unknown Camera fields: {sorted(unknown)}")
        kw.update(changes)
        K, dist, size = kw.pop("K"), kw.pop("dist"), kw.pop("image_size")
        return Camera(K, dist, size, **kw)

    def with_pose(self, pose: Optional[CameraPose]) -> "Camera":
        """Copy with ``pose`` set (or cleared with ``None``)."""
        return self.replace(pose=pose)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return (np.array_equal(self._K, other._K) and np.array_equal(self._dist, other._dist)
                and self._size == other._size and self.pose == other.pose
                and self.name == other.name and self.info == other.info)

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        w, h = self._size
        return (f"Camera({w}x{h}, fx={self.fx:.2f}, fy={self.fy:.2f}, cx={self.cx:.2f}, "
                f"cy={self.cy:.2f}, dist={np.array2string(self._dist, precision=4)}, "
                f"pose={self.pose!r})")

    # -- adaptation to a photo -----------------------------------------------------------
    def image_rotation(self, width: int, height: int) -> int:
        """Rotation (degrees clockwise) :meth:`for_image` assumes for a ``width x height`` photo.

        0 when the photo has the calibration orientation (or is square). When width and height
        are swapped: 90 if the camera was calibrated in landscape (a phone's upright portrait
        photo, EXIF orientation 6, is its landscape sensor image turned 90 degrees clockwise),
        270 if it was calibrated in portrait.

        Raises
        ------
        CameraFileError
            The aspect ratio differs in both orientations (a cropped photo).
        """
        w0, h0 = self._size
        if _same_aspect(w0, h0, width, height):
            return 0
        if _same_aspect(h0, w0, width, height):
            return 90 if w0 >= h0 else 270
        raise CameraFileError(
            f"photo is {width}x{height} (aspect {width / height:.4f}) but the camera was "
            f"calibrated at {w0}x{h0} (aspect {w0 / h0:.4f}); cropped photos cannot use this "
            f"calibration (use the full frame, or calibrate at this size)")

    def for_image(self, width: int, height: int, *, rotation: Optional[int] = None) -> "Camera":
        """The camera for a photo of ``width x height`` pixels taken with this camera.

        Parameters
        ----------
        width, height : int
            Size of the photo (after EXIF orientation, as :func:`load_photo` returns it).
        rotation : {None, 0, 90, 180, 270}, optional
            How the photo is turned relative to the calibration images, degrees clockwise
            (``cv2.rotate(calib_image, cv2.ROTATE_90_CLOCKWISE)`` is 90). ``None`` guesses it
            from the size with :meth:`image_rotation`.

        Returns
        -------
        Camera
            ``self`` when nothing changes; otherwise a camera with ``K`` rotated and rescaled,
            the distortion rotated with it (for 90 degrees clockwise ``p1' = p2``,
            ``p2' = -p1``, ``s1' = -s3``, ``s2' = -s4``, ``s3' = s1``, ``s4' = s2``; radial
            terms unchanged), the pose's camera frame rotated, and ``info`` dropped.

        Raises
        ------
        CameraFileError
            The photo has another aspect ratio (crop) or does not fit ``rotation``.

        Notes
        -----
        Uses the pixel-centre convention (module docstring): a rescale by ``s`` gives
        ``fx' = s fx`` and ``cx' = s (cx + 0.5) - 0.5``; a 90 degree clockwise turn gives
        ``fx' = fy, fy' = fx, cx' = H - 1 - cy, cy' = cx``.
        """
        width, height = int(width), int(height)
        if width <= 0 or height <= 0:
            raise ValueError(f"photo size must be positive, got {width}x{height}")
        if rotation is None:
            rotation = self.image_rotation(width, height)
        if rotation not in (0, 90, 180, 270):
            raise ValueError(f"rotation must be 0, 90, 180 or 270, got {rotation!r}")
        if rotation == 0 and (width, height) == self._size:
            return self
        K = self._K.copy()
        dist = self._dist.copy()
        w0, h0 = self._size
        if rotation and abs(K[0, 1]) > 1e-12:
            raise CameraFileError("cannot rotate a camera matrix with skew")
        for _ in range(rotation // 90):
            fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
            K = np.array([[fy, 0.0, h0 - 1.0 - cy], [0.0, fx, cx], [0.0, 0.0, 1.0]])
            dist = _rotate_dist(dist)
            w0, h0 = h0, w0
        if not _same_aspect(w0, h0, width, height):
            raise CameraFileError(
                f"photo is {width}x{height} but the camera calibrated at "
                f"{self._size[0]}x{self._size[1]} turned by {rotation} degrees is {w0}x{h0}; "
                f"cropped photos cannot use this calibration")
        sx, sy = width / w0, height / h0
        K[0, 0] *= sx
        K[0, 1] *= sx
        K[0, 2] = sx * (K[0, 2] + 0.5) - 0.5
        K[1, 1] *= sy
        K[1, 2] = sy * (K[1, 2] + 0.5) - 0.5
        pose = self.pose.rotated_photo(rotation) if (self.pose is not None and rotation) \
            else self.pose
        return Camera(K, dist, (width, height), pose=pose, name=self.name, info=None)

    # -- projection and undistortion -----------------------------------------------------
    def project(self, points_camera: Any) -> np.ndarray:
        """Project 3D points given in the camera frame to distorted pixel coordinates.

        Parameters
        ----------
        points_camera : array_like, shape (N, 3)
            Points in metres, camera frame (z forward, z > 0 in front).

        Returns
        -------
        numpy.ndarray
            (N, 2) float64 pixel coordinates ``(x, y)``.
        """
        import cv2

        X = np.asarray(points_camera, dtype=np.float64)
        if X.ndim != 2 or X.shape[1] != 3:
            raise ValueError(f"points_camera must have shape (N, 3), got {X.shape}")
        if len(X) == 0:
            return np.zeros((0, 2))
        uv, _ = cv2.projectPoints(X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self._K,
                                  self._dist)
        return uv.reshape(-1, 2)

    def undistort_points(self, points: Any, *, K_new: Any = None,
                         normalized: bool = False) -> np.ndarray:
        """Remove the lens distortion from pixel coordinates.

        Parameters
        ----------
        points : array_like, shape (N, 2)
            Distorted pixel coordinates ``(x, y)`` in this camera's image.
        K_new : array_like, shape (3, 3), optional
            Camera matrix of the output (e.g. from :meth:`undistort_image`); default ``K``.
        normalized : bool, optional
            Return normalized coordinates ``(X/Z, Y/Z)`` instead of pixels.

        Returns
        -------
        numpy.ndarray
            (N, 2) float64 undistorted coordinates.
        """
        import cv2

        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise ValueError(f"points must have shape (N, 2), got {pts.shape}")
        if len(pts) == 0:
            return np.zeros((0, 2))
        P = None if normalized else (self._K if K_new is None else np.asarray(K_new, np.float64))
        if P is not None and P.shape != (3, 3):
            raise ValueError(f"K_new must have shape (3, 3), got {P.shape}")
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        out = cv2.undistortPoints(pts.reshape(-1, 1, 2), self._K, self._dist, None, None, P, crit)
        return out.reshape(-1, 2)

    def undistort_image(self, image: np.ndarray, *, alpha: float = 0.0,
                        interpolation: Optional[int] = None) -> tuple[np.ndarray, np.ndarray]:
        """Resample a photo to an ideal pinhole camera without distortion.

        Parameters
        ----------
        image : numpy.ndarray, shape (H, W) or (H, W, C)
            Photo of exactly ``image_size`` (call :meth:`for_image` first otherwise).
        alpha : float, optional
            0 keeps only valid pixels (no black border), 1 keeps every source pixel
            (``cv2.getOptimalNewCameraMatrix``).
        interpolation : int, optional
            OpenCV interpolation flag, default ``cv2.INTER_LINEAR``.

        Returns
        -------
        undistorted : numpy.ndarray
            Same shape and dtype as ``image``.
        K_new : numpy.ndarray
            (3, 3) float64 camera matrix of ``undistorted`` (no distortion).
        """
        import cv2

        if not isinstance(image, np.ndarray) or image.ndim not in (2, 3):
            raise ValueError("image must be a numpy array of shape (H, W) or (H, W, C)")
        h, w = image.shape[:2]
        if (w, h) != self._size:
            raise ValueError(f"image is {w}x{h} but the camera is {self.width}x{self.height}; "
                             f"use camera.for_image({w}, {h}) first")
        if not 0.0 <= alpha <= 1.0:
            raise ValueError(f"alpha must be in [0, 1], got {alpha}")
        K_new, _ = cv2.getOptimalNewCameraMatrix(self._K, self._dist, self._size, alpha,
                                                 self._size)
        m1, m2 = cv2.initUndistortRectifyMap(self._K, self._dist, None, K_new, self._size,
                                             cv2.CV_32FC1)
        interp = cv2.INTER_LINEAR if interpolation is None else interpolation
        out = cv2.remap(image, m1, m2, interp, borderMode=cv2.BORDER_CONSTANT)
        return out, np.asarray(K_new, dtype=np.float64)

    # -- files -----------------------------------------------------------------------------
    @classmethod
    def load(cls, path: "PathLike") -> "Camera":
        """Read a camera file; see :func:`monodbh.calib.load_camera`."""
        from .camera_io import load_camera

        return load_camera(path)

    def save(self, path: "PathLike", format: str = "opencv") -> None:
        """Write a camera file; see :func:`monodbh.calib.save_camera`."""
        from .camera_io import save_camera

        save_camera(self, path, format=format)


def _same_aspect(w0: int, h0: int, w: int, h: int) -> bool:
    """True when ``w x h`` is ``w0 x h0`` rescaled, allowing one pixel of rounding per side."""
    sx, sy = w / w0, h / h0
    return abs(sx - sy) / max(sx, sy) <= 0.5 / w + 0.5 / h + 0.5 / w0 + 0.5 / h0
