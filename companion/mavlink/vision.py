"""Our pose to PX4 as external vision (ODOMETRY), converting map/FLU to PX4's NED/FRD.

The map frame is ENU with the body FLU (see :mod:`semmap.frames`); PX4 wants the pose of the
FRD body in local NED. With ``R_ned_enu`` swapping x/y and flipping z, and ``R_flu_frd``
flipping y and z::

    p_ned = R_ned_enu @ p_map
    R_ned_frd = R_ned_enu @ R_map_flu @ R_flu_frd

The message is ODOMETRY with ``frame_id = MAV_FRAME_LOCAL_NED``, ``child_frame_id =
MAV_FRAME_BODY_FRD`` and ``estimator_type = MAV_ESTIMATOR_TYPE_VISION``; unknown velocities,
rates and covariances are NaN, which PX4 reads as "not provided".
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from pymavlink.dialects.v20 import common as mavlink
from scipy.spatial.transform import Rotation

from companion.mavlink.link import MavlinkLink
from semmap.frames import Transform

R_NED_ENU: NDArray[np.float64] = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
R_FLU_FRD: NDArray[np.float64] = np.diag([1.0, -1.0, -1.0])

_NAN21 = [math.nan] * 21


def ned_pose_from_map(T_map_body: Transform) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(position (3,) NED metres, rotation (3, 3) FRD->NED) from a (4, 4) map-frame FLU pose."""
    T = np.asarray(T_map_body, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"T_map_body must be a finite (4, 4) transform (got shape {T.shape})")
    p_ned = R_NED_ENU @ T[:3, 3]
    R_ned_frd = R_NED_ENU @ T[:3, :3] @ R_FLU_FRD
    return p_ned, R_ned_frd


def quaternion_wxyz(R: NDArray[np.float64]) -> tuple[float, float, float, float]:
    """Unit quaternion (w, x, y, z), MAVLink's order, of a (3, 3) rotation."""
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    if w < 0.0:  # one canonical sign
        x, y, z, w = -x, -y, -z, -w
    return float(w), float(x), float(y), float(z)


def vision_odometry_message(
    link: MavlinkLink,
    T_map_body: Transform,
    time_usec: int,
    *,
    velocity_map_m_s: NDArray[np.float64] | None = None,
    quality_percent: int = 100,
    reset_counter: int = 0,
) -> mavlink.MAVLink_odometry_message:
    """ODOMETRY for PX4's EKF2 external-vision fusion.

    ``T_map_body``: (4, 4) pose of the FLU body in the map frame. ``time_usec``: capture time
    of the pose (microseconds, our boot clock). ``velocity_map_m_s``: optional (3,) velocity
    in the map frame (sent in body FRD as PX4 expects), else NaN. ``reset_counter``: bump it
    when the pose jumps (relocalisation) so EKF2 resets instead of rejecting it.
    """
    p_ned, R_ned_frd = ned_pose_from_map(T_map_body)
    if velocity_map_m_s is not None:
        v_frd = R_ned_frd.T @ (R_NED_ENU @ np.asarray(velocity_map_m_s, dtype=np.float64))
        vx, vy, vz = (float(v) for v in v_frd)
    else:
        vx = vy = vz = math.nan
    return link.mav.odometry_encode(
        time_usec, mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_FRD,
        float(p_ned[0]), float(p_ned[1]), float(p_ned[2]), list(quaternion_wxyz(R_ned_frd)),
        vx, vy, vz, math.nan, math.nan, math.nan, _NAN21, _NAN21,
        reset_counter & 0xFF, mavlink.MAV_ESTIMATOR_TYPE_VISION, int(max(-1, min(100, quality_percent))),
    )
