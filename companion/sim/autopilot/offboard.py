"""Offboard setpoint messages -> controller targets, the way PX4 interprets them.

``SET_POSITION_TARGET_LOCAL_NED`` and ``SET_POSITION_TARGET_GLOBAL_INT`` carry a ``type_mask``
whose bits say which fields to *ignore*; PX4 supports the local frames LOCAL_NED,
LOCAL_OFFSET_NED, BODY_NED and BODY_OFFSET_NED. ``SET_ATTITUDE_TARGET`` has no position at
all; the kinematic model flies it as a velocity command (tilt -> horizontal speed, thrust ->
climb rate), which is enough for a client to see the vehicle respond.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from companion.geo import GeoOrigin
from companion.sim.autopilot.vehicle import GRAVITY_M_S2, Target

IGNORE_PX = mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE
IGNORE_PY = mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE
IGNORE_PZ = mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE
IGNORE_VX = mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE
IGNORE_VY = mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE
IGNORE_VZ = mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE
IGNORE_YAW = mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE
IGNORE_YAW_RATE = mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE

LOCAL_FRAMES = frozenset({
    mavlink.MAV_FRAME_LOCAL_NED,
    mavlink.MAV_FRAME_LOCAL_OFFSET_NED,
    mavlink.MAV_FRAME_BODY_NED,
    mavlink.MAV_FRAME_BODY_OFFSET_NED,
})
GLOBAL_SETPOINT_FRAMES = frozenset({
    mavlink.MAV_FRAME_GLOBAL_INT,
    mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
})


class UnsupportedSetpointError(ValueError):
    """The setpoint uses a frame or combination PX4 would ignore."""


@dataclass(frozen=True)
class ReceivedSetpoint:
    """An offboard setpoint as received, with the target the mock derived from it (NED)."""

    stamp_s: float  # mock clock (seconds since start)
    msg_type: str
    frame: int
    type_mask: int
    target: Target


def _masked(values: tuple[float, float, float], mask: int,
            bits: tuple[int, int, int]) -> tuple[float, float, float] | None:
    out = tuple(math.nan if mask & b else float(v) for v, b in zip(values, bits, strict=True))
    if all(math.isnan(v) for v in out):
        return None
    return out  # type: ignore[return-value]


def _rotate_yaw(v: tuple[float, float, float], yaw_rad: float) -> tuple[float, float, float]:
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return (c * v[0] - s * v[1], s * v[0] + c * v[1], v[2])


def _yaw_fields(msg: Any) -> tuple[float | None, float | None]:
    yaw = None if msg.type_mask & IGNORE_YAW else float(msg.yaw)
    rate = None if msg.type_mask & IGNORE_YAW_RATE else float(msg.yaw_rate)
    return yaw, rate


def target_from_local_ned(msg: Any, position_ned_m: tuple[float, float, float],
                          yaw_rad: float) -> Target:
    """Target of a ``SET_POSITION_TARGET_LOCAL_NED`` given the vehicle's current pose."""
    frame = int(msg.coordinate_frame)
    if frame not in LOCAL_FRAMES:
        raise UnsupportedSetpointError(f"coordinate_frame {frame} not supported")
    pos = _masked((msg.x, msg.y, msg.z), msg.type_mask, (IGNORE_PX, IGNORE_PY, IGNORE_PZ))
    vel = _masked((msg.vx, msg.vy, msg.vz), msg.type_mask, (IGNORE_VX, IGNORE_VY, IGNORE_VZ))
    if frame in (mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED):
        if vel is not None:
            vel = _rotate_yaw(vel, yaw_rad)
        if pos is not None and frame == mavlink.MAV_FRAME_BODY_OFFSET_NED:
            pos = _rotate_yaw(pos, yaw_rad)
    if pos is not None and frame in (mavlink.MAV_FRAME_LOCAL_OFFSET_NED,
                                     mavlink.MAV_FRAME_BODY_OFFSET_NED):
        pos = tuple(p + c for p, c in zip(pos, position_ned_m, strict=True))  # type: ignore[assignment]
    yaw, rate = _yaw_fields(msg)
    if pos is None and vel is None and yaw is None and rate is None:
        raise UnsupportedSetpointError("type_mask ignores every field")
    return Target(position_ned_m=pos, velocity_ned_m_s=vel, yaw_rad=yaw, yaw_rate_rad_s=rate)


def target_from_global_int(msg: Any, home: GeoOrigin) -> Target:
    """Target of a ``SET_POSITION_TARGET_GLOBAL_INT`` (lat/lon degE7, alt metres)."""
    frame = int(msg.coordinate_frame)
    if frame not in GLOBAL_SETPOINT_FRAMES:
        raise UnsupportedSetpointError(f"coordinate_frame {frame} not supported")
    pos = None
    if not msg.type_mask & (IGNORE_PX | IGNORE_PY | IGNORE_PZ):
        alt_amsl = msg.alt if frame == mavlink.MAV_FRAME_GLOBAL_INT else home.alt_m + msg.alt
        pos = home.to_ned(msg.lat_int * 1e-7, msg.lon_int * 1e-7, alt_amsl)
    vel = _masked((msg.vx, msg.vy, msg.vz), msg.type_mask, (IGNORE_VX, IGNORE_VY, IGNORE_VZ))
    yaw, rate = _yaw_fields(msg)
    if pos is None and vel is None and yaw is None and rate is None:
        raise UnsupportedSetpointError("type_mask ignores every field")
    return Target(position_ned_m=pos, velocity_ned_m_s=vel, yaw_rad=yaw, yaw_rate_rad_s=rate)


def target_from_attitude(msg: Any, max_speed_up_m_s: float) -> Target:
    """Kinematic reading of ``SET_ATTITUDE_TARGET``: tilt gives horizontal velocity
    (``g * tan(tilt) * 1 s``), thrust 0.5 is hover and the rest maps linearly to climb rate."""
    w, x, y, z = (float(v) for v in msg.q)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if n < 1e-6:
        raise UnsupportedSetpointError("zero quaternion")
    w, x, y, z = w / n, x / n, y / n, z / n
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    v_fwd = -GRAVITY_M_S2 * math.tan(pitch)
    v_right = GRAVITY_M_S2 * math.tan(roll)
    vn, ve, _ = _rotate_yaw((v_fwd, v_right, 0.0), yaw)
    vd = -(float(msg.thrust) - 0.5) * 2.0 * max_speed_up_m_s
    return Target(velocity_ned_m_s=(vn, ve, vd), yaw_rad=yaw)
