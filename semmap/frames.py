"""Rigid transforms and the project's frame conventions.

Frames (all right-handed, metres, radians):

* ``map``: the 2D grid's frame, ENU-like: x east, y north, z up. The grid lies in the z = 0
  plane (the floor). ROS REP-103 convention, so exported maps load in standard tools.
* ``body``: FLU, x forward, y left, z up, origin at the vehicle's centre.
* ``camera``: optical, x right, y down, z forward (OpenCV / RealSense convention).
* ``ned``: PX4's local frame, x north, y east, z down, and ``frd``: PX4's body frame, x
  forward, y right, z down. Only :mod:`companion` speaks NED/FRD; every conversion to and
  from them (positions, yaw, rotations, quaternions) lives here so it is written exactly once.

Quaternions are (w, x, y, z), MAVLink's order, unless a name says otherwise.

Poses are 4x4 homogeneous matrices named ``T_<to>_<from>``: ``T_map_body`` maps body-frame
points into the map frame, and composition reads left to right:
``T_map_camera = T_map_body @ T_body_camera``. (The reference design's eq. 7 *adds* the robot
pose to the camera transform; that is only right for a pure translation. We compose in SE(3).)
"""

from __future__ import annotations

import math
from typing import overload

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

Transform = NDArray[np.float64]  # (4, 4)

#: ENU <-> NED axes (x and y swapped, z negated), its own inverse: ``v_ned = R_NED_ENU @ v_enu``.
R_NED_ENU: NDArray[np.float64] = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: FRD <-> FLU body axes (y and z negated), its own inverse: ``v_flu = R_FLU_FRD @ v_frd``.
R_FLU_FRD: NDArray[np.float64] = np.diag([1.0, -1.0, -1.0])

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


def rotation_from_quaternion_wxyz(q_wxyz: tuple[float, float, float, float]) -> NDArray[np.float64]:
    """(3, 3) rotation from a quaternion in (w, x, y, z) order (MAVLink's), normalised first."""
    w, x, y, z = q_wxyz
    return quaternion_to_rotation(x, y, z, w)


def quaternion_wxyz_from_rotation(R: NDArray[np.float64]) -> tuple[float, float, float, float]:
    """Unit quaternion (w, x, y, z) of a (3, 3) rotation, with w >= 0 (one canonical sign)."""
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    if w < 0.0:
        x, y, z, w = -x, -y, -z, -w
    return float(w), float(x), float(y), float(z)


def quaternion_wxyz_from_rpy(roll_rad: float, pitch_rad: float, yaw_rad: float) -> tuple[float, float, float, float]:
    """Unit quaternion (w, x, y, z) of Z-Y-X Euler angles (:func:`rotation_from_rpy`)."""
    cr, sr = math.cos(roll_rad / 2), math.sin(roll_rad / 2)
    cp, sp = math.cos(pitch_rad / 2), math.sin(pitch_rad / 2)
    cy, sy = math.cos(yaw_rad / 2), math.sin(yaw_rad / 2)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)


@overload
def wrap_angle_rad(angle_rad: float) -> float: ...


@overload
def wrap_angle_rad(angle_rad: NDArray[np.float64]) -> NDArray[np.float64]: ...


def wrap_angle_rad(angle_rad: float | NDArray[np.float64]) -> float | NDArray[np.float64]:
    """Wrap an angle (or an array of them, element-wise) to [-pi, pi)."""
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


# --- map pose (ENU/FLU) <-> PX4 pose (NED/FRD) ---------------------------------------------

def ned_pose_from_map(T_map_body: Transform) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(position (3,) NED metres, rotation (3, 3) FRD->NED) from a (4, 4) map-frame FLU pose."""
    T = np.asarray(T_map_body, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"T_map_body must be a finite (4, 4) transform (got shape {T.shape})")
    return R_NED_ENU @ T[:3, 3], R_NED_ENU @ T[:3, :3] @ R_FLU_FRD


def map_pose_from_ned(position_ned_m: tuple[float, float, float],
                      rpy_frd_rad: tuple[float, float, float]) -> Transform:
    """(4, 4) pose of the FLU body in the map frame (ENU) from PX4's local NED position and
    FRD attitude (roll, pitch, yaw from north): the inverse of :func:`ned_pose_from_map`."""
    R_ned_frd = rotation_from_rpy(*rpy_frd_rad)
    return make_transform(R_NED_ENU @ R_ned_frd @ R_FLU_FRD, R_NED_ENU @ np.asarray(position_ned_m, dtype=np.float64))
