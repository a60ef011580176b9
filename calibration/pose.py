"""Mounting pose: probe frame -> room frame, from installer angles or a board on the floor.

Both frames are right-handed with +y up (CONVENTIONS.md); ``lightprobe.core.calibration.Pose`` maps
``x_room = R x_probe + position``.

Installer angles (:func:`pose_from_angles`):

* ``heading_deg``: room azimuth of the probe's front mark (probe azimuth 0). Azimuth follows
  the CONVENTIONS formula ``d = (sin phi, 0, -cos phi)`` on the horizon, so heading 90 turns the
  front mark from room -z to room +x. It is a rotation about +y by ``-heading``.
* ``tilt_deg`` towards ``tilt_azimuth_deg``: the probe's zenith leans by ``tilt_deg`` towards the
  room-horizontal direction of azimuth ``tilt_azimuth_deg`` (applied after the heading).

Board on the floor (:func:`pose_from_board`): the board's +x axis defines room azimuth 0 (room
-z), its normal towards the camera defines room +y; the board origin is the inner corner with a
black square diagonally outside it (``lightprobe.calibration.fisheye.orient_corners``; use a board with one
even and one odd corner count, else the heading is ambiguous by 180 degrees); ``cv2.fisheye.solvePnP`` (OpenCV >= 4.9)
gives the board pose in the camera frame, and ``lightprobe.core.sphere.CAMERA_TO_PROBE`` links camera and
probe frames. Dtype policy: float64 throughout.
"""

from __future__ import annotations

import cv2
import numpy as np

from lightprobe.core.calibration import FisheyeModel, Pose
from lightprobe.core.sphere import CAMERA_TO_PROBE

__all__ = ["pose_from_angles", "pose_from_board", "rotation_angle_deg"]


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis, np.float64).reshape(3, 1) * angle)[0]


def pose_from_angles(heading_deg: float, tilt_deg: float = 0.0, tilt_azimuth_deg: float = 0.0,
                     position: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Pose:
    """Rotation from installer angles (module docs); angles in degrees, position in metres."""
    if not all(np.isfinite([heading_deg, tilt_deg, tilt_azimuth_deg])):
        raise ValueError("pose angles must be finite")
    R_head = _axis_angle(np.array([0.0, 1.0, 0.0]), -np.radians(heading_deg))
    a = np.radians(tilt_azimuth_deg)
    toward = np.array([np.sin(a), 0.0, -np.cos(a)])
    axis = np.cross(np.array([0.0, 1.0, 0.0]), toward)  # rotates +y towards `toward`
    R_tilt = _axis_angle(axis / np.linalg.norm(axis), np.radians(tilt_deg))
    return Pose(R_tilt @ R_head, np.asarray(position, np.float64))


def pose_from_board(corners: np.ndarray, object_points: np.ndarray, fisheye: FisheyeModel) -> Pose:
    """Probe -> room rotation from one view of a board lying on the floor.

    ``corners`` (N, 2) pixels and ``object_points`` (N, 3) on z = 0 in board units. Raises
    ValueError when solvePnP fails.
    """
    ok, rvec, tvec = cv2.fisheye.solvePnP(np.asarray(object_points, np.float64).reshape(-1, 1, 3),
                                          np.asarray(corners, np.float64).reshape(-1, 1, 2),
                                          fisheye.K, fisheye.D.reshape(4, 1))
    if not ok:
        raise ValueError("solvePnP found no board pose")
    R_cam_board = cv2.Rodrigues(rvec)[0]
    t = tvec.reshape(3)
    # Board axes in the camera frame; the normal must point towards the camera (room up).
    bx, bz = R_cam_board[:, 0], R_cam_board[:, 2]
    if bz @ (-t) < 0:
        bz = -bz
    by_room = bz  # room +y
    mz_room = bx - (bx @ by_room) * by_room  # room -z (azimuth 0) = board +x, orthogonalised
    mz_room /= np.linalg.norm(mz_room)
    x_room = np.cross(by_room, -mz_room)  # x = y cross z
    R_room_cam = np.stack([x_room, by_room, -mz_room], axis=0)  # rows: room axes in camera frame
    R = R_room_cam @ CAMERA_TO_PROBE.T  # probe -> camera -> room
    return Pose(R, np.zeros(3))


def rotation_angle_deg(R1: np.ndarray, R2: np.ndarray) -> float:
    """Angle (deg) of the rotation R1^T R2."""
    c = (np.trace(np.asarray(R1).T @ np.asarray(R2)) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
