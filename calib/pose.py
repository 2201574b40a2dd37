"""Camera pose over level ground from one photo of a board lying on the ground.

For crews shooting from a pole of fixed height: photograph the calibration board lying flat
on level ground once, and :func:`estimate_ground_pose` turns it into the camera's height above
the ground and its pitch and roll (``solvePnP``), stored in cam.yaml. See
:mod:`monodbh.calib.camera` for the frames and sign conventions (pitch > 0 looks up).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np

from .board import Board, detect_board
from .camera import _M90, Camera, CameraPose, _rz
from .errors import CalibrationError

__all__ = ["estimate_ground_pose", "GroundPoseResult", "pose_from_board"]


@dataclass
class GroundPoseResult:
    """Outcome of :func:`estimate_ground_pose`.

    Attributes
    ----------
    camera : Camera
        The input camera (calibration size and orientation) with ``pose`` set.
    pose : CameraPose
        The pose, in the calibration camera frame.
    rms_px : float
        RMS reprojection error of the board corners, pixels of the photo.
    distance_m : float
        Distance from the camera centre to the nearest board corner, metres.
    n_corners : int
        Corners used.
    rotation : int
        Rotation of the photo relative to the calibration images (degrees clockwise).
    warnings : list of str
        Reasons to distrust the result.
    """

    camera: Camera
    pose: CameraPose
    rms_px: float
    distance_m: float
    n_corners: int
    rotation: int
    warnings: list = field(default_factory=list)


def pose_from_board(rvec: Any, tvec: Any, *, board_thickness_m: float = 0.0) -> CameraPose:
    """Ground pose from the board pose in the camera frame (``solvePnP`` output).

    Parameters
    ----------
    rvec, tvec : array_like, shape (3,)
        Board-to-camera transform (Rodrigues vector; translation, metres).
    board_thickness_m : float, optional
        Thickness of the board lying on the ground (added to the height).

    Returns
    -------
    CameraPose
        World z up (the board normal on the camera's side), origin on the ground below the
        camera, yaw removed (optical axis heading along world +x).
    """
    import cv2

    R_cb = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3))[0]
    t_cb = np.asarray(tvec, np.float64).reshape(3)
    C_b = -R_cb.T @ t_cb  # camera centre in board coordinates
    # The board's z axis points away from the camera when its corners run clockwise in the
    # image; world z must point to the camera's side of the ground.
    R_wb = np.diag([1.0, -1.0, -1.0]) if C_b[2] < 0 else np.eye(3)
    R_wc = R_wb @ R_cb.T
    height = float((R_wb @ C_b)[2]) + float(board_thickness_m)
    f = R_wc[:, 2]
    if math.hypot(f[0], f[1]) > 1e-9:
        yaw = math.atan2(f[1], f[0])
    else:  # looking straight down: use the image's "up" direction
        u = -R_wc[:, 1]
        yaw = math.atan2(u[1], u[0])
    R_wc = _rz(-yaw) @ R_wc
    U, _, Vt = np.linalg.svd(R_wc)  # re-orthonormalise against rounding
    return CameraPose(U @ Vt, [0.0, 0.0, height])


def estimate_ground_pose(image: Any, camera: Camera, board: Board, *,
                         board_thickness_m: float = 0.0, detector: str = "auto",
                         max_side: int = 1000, name: Optional[str] = None) -> GroundPoseResult:
    """Estimate camera height, pitch and roll from a photo of a board lying on level ground.

    Parameters
    ----------
    image : path or numpy.ndarray
        The photo (file, or ``(H, W)`` gray / ``(H, W, 3)`` RGB uint8), any resolution with the
        calibration's aspect ratio, either orientation.
    camera : Camera
        Calibrated camera (``for_image`` adapts it to the photo).
    board : Board
        The board in the photo.
    board_thickness_m : float, optional
        Thickness of the board (its top surface is that far above the ground).
    detector, max_side
        Detection settings, see :func:`~monodbh.calib.board.detect_board`.
    name : str, optional
        Name for messages (default: the path).

    Returns
    -------
    GroundPoseResult
        ``result.camera`` is ``camera`` with the pose set, ready to save.

    Raises
    ------
    PhotoError
        The photo cannot be read.
    CameraFileError
        The photo's aspect ratio does not fit the calibration.
    CalibrationError
        The board is not found or the pose cannot be solved.
    """
    import cv2

    from .calibration import _to_gray

    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a Camera, got {type(camera).__name__}")
    if not isinstance(board, Board):
        raise TypeError(f"board must be a Board, got {type(board).__name__}")
    label = name or (str(image) if not isinstance(image, np.ndarray) else "image")
    gray = _to_gray(image)
    h, w = gray.shape
    rotation = camera.image_rotation(w, h)
    cam = camera.for_image(w, h, rotation=rotation)
    det = detect_board(gray, board, detector=detector, max_side=max_side)
    if det is None:
        raise CalibrationError(f"{label}: board ({board.describe()}) not found")
    obj = board.object_points()[det.ids].astype(np.float64)
    img = det.corners.astype(np.float64)
    K, dist = np.asarray(cam.K), np.asarray(cam.dist)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CalibrationError(f"{label}: cannot solve the board pose")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    rms = float(np.sqrt(((proj.reshape(-1, 2) - img) ** 2).sum(axis=1).mean()))
    pose_photo = pose_from_board(rvec, tvec, board_thickness_m=board_thickness_m)
    # Back to the calibration camera frame: X_photo = M @ X_cal.
    M = np.linalg.matrix_power(_M90, (rotation // 90) % 4)
    pose = CameraPose(pose_photo.R_world_from_camera @ M, pose_photo.t_world_from_camera)
    R_cb = cv2.Rodrigues(rvec)[0]
    dists = np.linalg.norm(obj @ R_cb.T + tvec.reshape(1, 3), axis=1)
    warnings = []
    if rms > 2.0:
        warnings.append(f"board reprojection error {rms:.2f} px is high: is the board flat, "
                        f"and is cam.yaml the calibration of this camera?")
    if pose.height_m <= 0.05:
        warnings.append(f"camera height {pose.height_m:.3f} m is implausible")
    # Angle between the board normal and the line of sight to the board origin.
    cos_view = abs(float(R_cb[:, 2] @ tvec.ravel())) / max(float(np.linalg.norm(tvec)), 1e-12)
    view_angle = math.degrees(math.acos(min(1.0, cos_view)))
    if abs(pose.roll_deg) > 45.0:
        warnings.append(f"roll {pose.roll_deg:+.0f} deg: is the board really lying on the ground "
                        f"(not held up), and the photo upright?")
    if view_angle > 75.0:
        warnings.append(f"board seen at a grazing angle ({view_angle:.0f} deg): pitch and height "
                        f"are uncertain; photograph it from higher up or closer")
    return GroundPoseResult(camera=camera.with_pose(pose), pose=pose, rms_px=rms,
                            distance_m=float(dists.min()), n_corners=int(len(obj)),
                            rotation=rotation, warnings=warnings)
