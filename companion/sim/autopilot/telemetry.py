"""Telemetry messages the mock autopilot streams, built from one state snapshot.

Each encoder takes the pymavlink ``MAVLink`` object and a :class:`Snapshot` and returns a
message. :data:`STREAMS` names them with PX4-like default rates (PX4's "onboard" MAVLink mode:
ATTITUDE at 100 Hz, which the companion interpolates camera poses from; lowered where a fast
stream would only load a test machine: ATTITUDE_QUATERNION, GLOBAL_POSITION_INT); clients change rates with
``MAV_CMD_SET_MESSAGE_INTERVAL`` and ask for one message with ``MAV_CMD_REQUEST_MESSAGE``.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from companion import px4
from companion.geo import GeoOrigin
from companion.px4 import FlightMode
from companion.sim.autopilot.vehicle import VehicleState

#: Sensors PX4 SITL reports present/enabled/healthy (no RC receiver).
SENSORS_OK = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
    | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mavlink.MAV_SYS_STATUS_SENSOR_GPS
    | mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | mavlink.MAV_SYS_STATUS_SENSOR_YAW_POSITION
    | mavlink.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | mavlink.MAV_SYS_STATUS_AHRS
    | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
    | mavlink.MAV_SYS_STATUS_PREARM_CHECK
)

#: The SYS_STATUS health bit each simulated sensor failure clears (MAV_CMD_INJECT_FAILURE).
FAILURE_UNIT_SENSOR_BITS = {
    mavlink.FAILURE_UNIT_SENSOR_GYRO: mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO,
    mavlink.FAILURE_UNIT_SENSOR_ACCEL: mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL,
    mavlink.FAILURE_UNIT_SENSOR_MAG: mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG,
    mavlink.FAILURE_UNIT_SENSOR_BARO: mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE,
    mavlink.FAILURE_UNIT_SENSOR_GPS: mavlink.MAV_SYS_STATUS_SENSOR_GPS,
}
#: Earth's magnetic field at PX4 SITL's home (Zurich), NED, gauss.
MAG_FIELD_NED_GAUSS = (0.21, 0.01, 0.43)

CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY
)

#: PX4 v1.15.0 official (major << 24 | minor << 16 | patch << 8 | FIRMWARE_VERSION_TYPE).
FLIGHT_SW_VERSION = (1 << 24) | (15 << 16) | (0 << 8) | mavlink.FIRMWARE_VERSION_TYPE_OFFICIAL


@dataclass(frozen=True)
class Snapshot:
    """Everything the telemetry encoders read, taken once per tick."""

    time_boot_ms: int
    time_usec: int
    vehicle: VehicleState
    home: GeoOrigin  # the local NED origin (PX4's EKF/global origin)
    home_ned_m: tuple[float, float, float]  # home (where the vehicle last armed), local NED
    mode: FlightMode
    armed: bool
    landed_state: int  # MAV_LANDED_STATE_*
    sensors_health: int  # MAV_SYS_STATUS_SENSOR_* bits currently healthy
    mission_seq: int
    mission_total: int
    mission_state: int  # MISSION_STATE_*
    battery_remaining_pct: int
    system_id: int
    gps_fix: bool = True  # False while a GPS failure is injected
    range_down_m: float | None = None  # the downward range finder's truth (SIH has one)


def quaternion_wxyz(roll_rad: float, pitch_rad: float, yaw_rad: float) -> tuple[float, ...]:
    """Unit quaternion (w, x, y, z) of Z-Y-X Euler angles (NED/FRD, as MAVLink sends it)."""
    cr, sr = math.cos(roll_rad / 2), math.sin(roll_rad / 2)
    cp, sp = math.cos(pitch_rad / 2), math.sin(pitch_rad / 2)
    cy, sy = math.cos(yaw_rad / 2), math.sin(yaw_rad / 2)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)


def heartbeat(mav: mavlink.MAVLink, s: Snapshot) -> Any:
    if s.armed:
        status = mavlink.MAV_STATE_ACTIVE
    else:
        status = mavlink.MAV_STATE_STANDBY
    return mav.heartbeat_encode(
        px4.MAV_TYPE_QUADROTOR, px4.MAV_AUTOPILOT_PX4,
        px4.encode_heartbeat_base_mode(s.mode, s.armed), s.mode.custom_mode, status)


def sys_status(mav: mavlink.MAVLink, s: Snapshot) -> Any:
    voltage_mv = int(16800 * (0.85 + 0.15 * s.battery_remaining_pct / 100.0))
    return mav.sys_status_encode(
        SENSORS_OK, SENSORS_OK, s.sensors_health, 250, voltage_mv, 1200 if s.armed else 50,
        s.battery_remaining_pct, 0, 0, 0, 0, 0, 0)


def extended_sys_state(mav: mavlink.MAVLink, s: Snapshot) -> Any:
    return mav.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_UNDEFINED, s.landed_state)


def attitude(mav: mavlink.MAVLink, s: Snapshot) -> Any:
    v = s.vehicle
    return mav.attitude_encode(s.time_boot_ms, v.roll_rad, v.pitch_rad, v.yaw_rad, 0.0, 0.0,
                               v.yaw_rate_rad_s)


def attitude_quaternion(mav: mavlink.MAVLink, s: Snapshot) -> Any:
    v = s.vehicle
    w, x, y, z = quaternion_wxyz(v.roll_rad, v.pitch_rad, v.yaw_rad)
    return mav.attitude_quaternion_encode(s.time_boot_ms, w, x, y, z, 0.0, 0.0, v.yaw_rate_rad_s)


def local_position_ned(mav: mavlink.MAVLink, s: Snapshot) -> Any:
    (n, e, d), (vn, ve, vd) = s.vehicle.position_ned_m, s.vehicle.velocity_ned_m_s
    return mav.local_position_ned_encode(s.time_boot_ms, n, e, d, vn, ve, vd)


def global_position_int(mav: mavlink.MAVLink, s: Snapshot) -> Any:
    (n, e, d), (vn, ve, vd) = s.vehicle.position_ned_m, s.vehicle.velocity_ned_m_s
    lat, lon, alt = s.home.to_global(n, e, d)
    hdg = int(round(math.degrees(s.vehicle.yaw_rad) % 360.0 * 100)) % 36000
    return mav.global_position_int_encode(
        s.time_boot_ms, int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
        int(round((s.home_ned_m[2] - d) * 1000)), int(round(vn * 100)), int(round(ve * 100)),
        int(round(vd * 100)), hdg)


#: The downward range finder's limits (cm), as SIH's.
RANGE_MIN_CM, RANGE_MAX_CM = 1, 4000


def distance_sensor(mav: mavlink.MAVLink, s: Snapshot) -> Any:
    """The downward range finder (orientation PITCH_270): the true height above the floor."""
    cm = RANGE_MAX_CM + 1 if s.range_down_m is None else int(round(max(s.range_down_m, 0.0) * 100))
    return mav.distance_sensor_encode(s.time_boot_ms, RANGE_MIN_CM, RANGE_MAX_CM, max(cm, RANGE_MIN_CM),
                                      mavlink.MAV_DISTANCE_SENSOR_LASER, 0, mavlink.MAV_SENSOR_ROTATION_PITCH_270, 255)


def home_position(mav: mavlink.MAVLink, s: Snapshot) -> Any:
    lat, lon, alt = s.home.to_global(*s.home_ned_m)
    hn, he, hd = s.home_ned_m
    return mav.home_position_encode(
        int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
        hn, he, hd, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, s.time_usec)


def gps_global_origin(mav: mavlink.MAVLink, s: Snapshot) -> Any:
    h = s.home
    return mav.gps_global_origin_encode(int(round(h.lat_deg * 1e7)), int(round(h.lon_deg * 1e7)),
                                        int(round(h.alt_m * 1000)), s.time_usec)


def gps_raw_int(mav: mavlink.MAVLink, s: Snapshot) -> Any:
    (n, e, d), (vn, ve, _vd) = s.vehicle.position_ned_m, s.vehicle.velocity_ned_m_s
    lat, lon, alt = s.home.to_global(n, e, d)
    cog = int(round(math.degrees(math.atan2(ve, vn)) % 360.0 * 100)) % 36000
    fix = mavlink.GPS_FIX_TYPE_3D_FIX if s.gps_fix else mavlink.GPS_FIX_TYPE_NO_FIX
    return mav.gps_raw_int_encode(
        s.time_usec, fix, int(round(lat * 1e7)), int(round(lon * 1e7)),
        int(round(alt * 1000)), 80, 120, int(round(math.hypot(vn, ve) * 100)), cog, 14 if s.gps_fix else 0)


def altitude(mav: mavlink.MAVLink, s: Snapshot) -> Any:
    d = s.vehicle.position_ned_m[2]
    amsl = s.home.alt_m - d
    rel = s.home_ned_m[2] - d
    # Terrain and bottom clearance: the height above the floor, which home stands on.
    return mav.altitude_encode(s.time_usec, amsl, amsl, -d, rel, rel, rel)


def vfr_hud(mav: mavlink.MAVLink, s: Snapshot) -> Any:
    (_n, _e, d), (vn, ve, vd) = s.vehicle.position_ned_m, s.vehicle.velocity_ned_m_s
    hdg = int(round(math.degrees(s.vehicle.yaw_rad))) % 360
    throttle = 50 if s.armed and s.landed_state != mavlink.MAV_LANDED_STATE_ON_GROUND else 0
    return mav.vfr_hud_encode(math.hypot(vn, ve), math.hypot(vn, ve), hdg, throttle,
                              s.home.alt_m - d, -vd)


def battery_status(mav: mavlink.MAVLink, s: Snapshot) -> Any:
    cell_mv = int(4200 * (0.85 + 0.15 * s.battery_remaining_pct / 100.0))
    cells = [cell_mv] * 4 + [65535] * 6
    return mav.battery_status_encode(
        0, mavlink.MAV_BATTERY_FUNCTION_ALL, mavlink.MAV_BATTERY_TYPE_LIPO, 2500, cells,
        1200 if s.armed else 50, -1, -1, s.battery_remaining_pct)


def mission_current(mav: mavlink.MAVLink, s: Snapshot) -> Any:
    mission_mode = 1 if s.mode is FlightMode.MISSION else 2
    return mav.mission_current_encode(s.mission_seq, s.mission_total, s.mission_state,
                                      mission_mode)


def odometry(mav: mavlink.MAVLink, s: Snapshot) -> Any:
    v = s.vehicle
    (n, e, d), (vn, ve, vd) = v.position_ned_m, v.velocity_ned_m_s
    q = quaternion_wxyz(v.roll_rad, v.pitch_rad, v.yaw_rad)
    # Velocity in the body frame, as PX4 sends it (child frame BODY_FRD).
    c, sn = math.cos(v.yaw_rad), math.sin(v.yaw_rad)
    vx_b, vy_b = c * vn + sn * ve, -sn * vn + c * ve
    nan21 = [math.nan] * 21
    return mav.odometry_encode(
        s.time_usec, mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_FRD, n, e, d, q,
        vx_b, vy_b, vd, 0.0, 0.0, v.yaw_rate_rad_s, nan21, nan21, 0,
        mavlink.MAV_ESTIMATOR_TYPE_NAIVE, 100)


def highres_imu(mav: mavlink.MAVLink, s: Snapshot) -> Any:
    """The IMU as a hovering vehicle's would read it: specific force and the earth's field in
    FRD body axes, the yaw rate, ISA pressure at the altitude."""
    v = s.vehicle
    cr, sr = math.cos(v.roll_rad), math.sin(v.roll_rad)
    cp, sp = math.cos(v.pitch_rad), math.sin(v.pitch_rad)
    cy, sy = math.cos(v.yaw_rad), math.sin(v.yaw_rad)
    # Rows of R_frd_ned (ZYX Euler): NED vectors into the body.
    rows = ((cp * cy, cp * sy, -sp),
            (sr * sp * cy - cr * sy, sr * sp * sy + cr * cy, sr * cp),
            (cr * sp * cy + sr * sy, cr * sp * sy - sr * cy, cr * cp))
    gravity = 9.80665
    acc = [-gravity * r[2] for r in rows]  # specific force holds the vehicle up: -g in NED
    mag = [sum(r[i] * MAG_FIELD_NED_GAUSS[i] for i in range(3)) for r in rows]
    alt_m = s.home.alt_m - v.position_ned_m[2]
    pressure_hpa = 1013.25 * (1.0 - 2.25577e-5 * alt_m) ** 5.25588
    return mav.highres_imu_encode(s.time_usec, acc[0], acc[1], acc[2], 0.0, 0.0, v.yaw_rate_rad_s,
                                  mag[0], mag[1], mag[2], pressure_hpa, 0.0, alt_m, 25.0, 0x1FFF, 0)


def autopilot_version(mav: mavlink.MAVLink, s: Snapshot) -> Any:
    return mav.autopilot_version_encode(
        CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0x26AC, 0x0011,
        0x4D4F434B00000000 + s.system_id)


_statustext_ids = itertools.count(1)


def statustext_chunks(mav: mavlink.MAVLink, severity: int, text: str) -> list[Any]:
    """STATUSTEXT for ``text``: one message, or for more than 50 characters numbered chunks
    sharing an ``id`` (MAVLink 2; PX4 sends up to 127 characters this way)."""
    data = text.encode("ascii", "replace")[:127]
    if len(data) <= 50:
        return [mav.statustext_encode(severity, data)]
    msg_id = next(_statustext_ids) % 65535 + 1
    chunks = [data[i:i + 50] for i in range(0, len(data), 50)]
    if len(data) % 50 == 0:
        chunks.append(b"")  # the terminating chunk a multiple of 50 characters needs
    return [mav.statustext_encode(severity, c, msg_id, seq) for seq, c in enumerate(chunks)]


Encoder = Callable[[mavlink.MAVLink, Snapshot], Any]

#: Streamed messages: name -> (message id, encoder, default rate in Hz; 0 = off).
STREAMS: dict[str, tuple[int, Encoder, float]] = {
    "HEARTBEAT": (mavlink.MAVLINK_MSG_ID_HEARTBEAT, heartbeat, 1.0),
    "SYS_STATUS": (mavlink.MAVLINK_MSG_ID_SYS_STATUS, sys_status, 2.0),
    "EXTENDED_SYS_STATE": (mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, extended_sys_state, 5.0),
    "ATTITUDE": (mavlink.MAVLINK_MSG_ID_ATTITUDE, attitude, 100.0),
    "ATTITUDE_QUATERNION": (mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, attitude_quaternion, 30.0),
    "LOCAL_POSITION_NED": (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, local_position_ned, 30.0),
    "GLOBAL_POSITION_INT": (mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, global_position_int, 30.0),
    "ODOMETRY": (mavlink.MAVLINK_MSG_ID_ODOMETRY, odometry, 10.0),
    "HOME_POSITION": (mavlink.MAVLINK_MSG_ID_HOME_POSITION, home_position, 0.5),
    "GPS_RAW_INT": (mavlink.MAVLINK_MSG_ID_GPS_RAW_INT, gps_raw_int, 5.0),
    "ALTITUDE": (mavlink.MAVLINK_MSG_ID_ALTITUDE, altitude, 10.0),
    "VFR_HUD": (mavlink.MAVLINK_MSG_ID_VFR_HUD, vfr_hud, 4.0),
    "BATTERY_STATUS": (mavlink.MAVLINK_MSG_ID_BATTERY_STATUS, battery_status, 1.0),
    "MISSION_CURRENT": (mavlink.MAVLINK_MSG_ID_MISSION_CURRENT, mission_current, 1.0),
    "HIGHRES_IMU": (mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, highres_imu, 0.0),
    "DISTANCE_SENSOR": (mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR, distance_sensor, 10.0),
}

#: Messages that can be requested once (MAV_CMD_REQUEST_MESSAGE) but are not streamed.
ON_REQUEST: dict[int, Encoder] = {
    mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: autopilot_version,
    mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN: gps_global_origin,
    **{msg_id: enc for msg_id, enc, _rate in STREAMS.values()},
}
