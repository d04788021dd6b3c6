"""Rigid transforms and the project's frame conventions.

Frames (all right-handed, metres, radians):

* ``map``: the 2D grid's frame, ENU-like: x east, y north, z up. The grid lies in the z = 0
  plane (the floor). ROS REP-103 convention, so exported maps load in standard tools.
* ``body``: FLU, x forward, y left, z up, origin at the vehicle's centre.
* ``camera``: optical, x right, y down, z forward (OpenCV / RealSense convention).
* ``ned``: PX4's local frame, x north, y east, z down. Only :mod:`companion` speaks NED; the
  conversion lives here so it is written exactly once.

Poses are 4x4 homogeneous matrices named ``T_<to>_<from>``: ``T_map_body`` maps body-frame
points into the map frame, and composition reads left to right:
``T_map_camera = T_map_body @ T_body_camera``. (The reference design's eq. 7 *adds* the robot
pose to the camera transform; that is only right for a pure translation. We compose in SE(3).)
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Transform = NDArray[np.float64]  # (4, 4)

#: Rotation taking optical-camera axes to FLU body axes for a camera looking along body +x.
R_BODY_CAMERA_FORWARD: NDArray[np.float64] = np.array(
    [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]
)


def make_transform(rotation: NDArray[np.float64], translation_m: NDArray[np.float64]) -> Transform:
    """Build a 4x4 transform from a (3, 3) rotation and a (3,) translation in metres."""
    T = np.eye(4)
    T[:3, :3] = rotation
    T[:3, 3] = translation_m
    return T


def invert(T: Transform) -> Transform:
    """Inverse of a rigid transform (uses R^T, not a general matrix inverse)."""
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def transform_points(T: Transform, points_m: NDArray[np.floating]) -> NDArray[np.float64]:
    """Apply ``T`` to (N, 3) points; returns (N, 3) float64."""
    pts = np.asarray(points_m, dtype=np.float64)
    return pts @ T[:3, :3].T + T[:3, 3]


def rot_x(angle_rad: float) -> NDArray[np.float64]:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle_rad: float) -> NDArray[np.float64]:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle_rad: float) -> NDArray[np.float64]:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_from_rpy(roll_rad: float, pitch_rad: float, yaw_rad: float) -> NDArray[np.float64]:
    """Z-Y-X (yaw, then pitch, then roll) rotation, the aerospace convention."""
    return rot_z(yaw_rad) @ rot_y(pitch_rad) @ rot_x(roll_rad)


def rpy_from_rotation(R: NDArray[np.float64]) -> tuple[float, float, float]:
    """Inverse of :func:`rotation_from_rpy`: (roll, pitch, yaw) in radians."""
    pitch = math.asin(max(-1.0, min(1.0, -R[2, 0])))
    roll = math.atan2(R[2, 1], R[2, 2])
    yaw = math.atan2(R[1, 0], R[0, 0])
    return roll, pitch, yaw


def pose_from_xyz_rpy(
    x_m: float, y_m: float, z_m: float, roll_rad: float = 0.0, pitch_rad: float = 0.0,
    yaw_rad: float = 0.0,
) -> Transform:
    """4x4 transform from a position and Z-Y-X Euler angles."""
    return make_transform(rotation_from_rpy(roll_rad, pitch_rad, yaw_rad), np.array([x_m, y_m, z_m]))


def quaternion_to_rotation(qx: float, qy: float, qz: float, qw: float) -> NDArray[np.float64]:
    """(3, 3) rotation from a unit quaternion in (x, y, z, w) order (TUM / ROS order)."""
    q = np.array([qw, qx, qy, qz], dtype=np.float64)
    n = float(np.linalg.norm(q))
    if n < 1e-12:
        raise ValueError("zero-norm quaternion")
    w, x, y, z = q / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def wrap_angle_rad(angle_rad: float) -> float:
    """Wrap an angle to [-pi, pi)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


# --- map (ENU) <-> PX4 local NED ---------------------------------------------------------

def enu_to_ned(x_east_m: float, y_north_m: float, z_up_m: float) -> tuple[float, float, float]:
    """Map-frame (ENU) position to PX4 local NED (north, east, down)."""
    return y_north_m, x_east_m, -z_up_m


def ned_to_enu(north_m: float, east_m: float, down_m: float) -> tuple[float, float, float]:
    """PX4 local NED position to map-frame ENU (x east, y north, z up)."""
    return east_m, north_m, -down_m


def yaw_enu_to_ned(yaw_enu_rad: float) -> float:
    """ENU yaw (from east, counter-clockwise) to NED yaw (from north, clockwise)."""
    return wrap_angle_rad(math.pi / 2.0 - yaw_enu_rad)


def yaw_ned_to_enu(yaw_ned_rad: float) -> float:
    """NED yaw (from north, clockwise) to ENU yaw (from east, counter-clockwise)."""
    return wrap_angle_rad(math.pi / 2.0 - yaw_ned_rad)
