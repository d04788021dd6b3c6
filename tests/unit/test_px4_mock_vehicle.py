"""The mock autopilot's pure parts: kinematic vehicle, setpoint interpretation, param encoding."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink

from companion.geo import GeoOrigin
from companion.px4 import (
    MAV_PARAM_TYPE_INT32,
    MAV_PARAM_TYPE_REAL32,
    FlightMode,
    decode_param_value,
    encode_param_value,
)
from companion.sim.autopilot import offboard
from companion.sim.autopilot.navigator import Navigator
from companion.sim.autopilot.params import ParamStore
from companion.sim.autopilot.vehicle import KinematicMulticopter, Target, VehicleLimits

DT = 0.01


def _fly(v: KinematicMulticopter, seconds: float) -> list[tuple[np.ndarray, np.ndarray]]:
    trace = []
    for _ in range(int(seconds / DT)):
        v.step(DT)
        trace.append((np.array(v.position_ned_m), np.array(v.velocity_ned_m_s)))
    return trace


def test_position_target_reached_within_limits_without_overshoot() -> None:
    lim = VehicleLimits(max_speed_xy_m_s=2.0, max_accel_xy_m_s2=2.0)
    v = KinematicMulticopter(lim)
    v.motors_on = True
    v.set_target(Target(position_ned_m=(0.0, 0.0, -2.0)))
    _fly(v, 4.0)
    assert v.position_ned_m[2] == pytest.approx(-2.0, abs=0.02)
    v.set_target(Target(position_ned_m=(6.0, 0.0, -2.0)))
    trace = _fly(v, 8.0)
    speeds = [math.hypot(vel[0], vel[1]) for _, vel in trace]
    assert max(speeds) <= lim.max_speed_xy_m_s + 1e-6
    accels = np.diff([vel[:2] for _, vel in trace], axis=0) / DT
    assert np.max(np.linalg.norm(accels, axis=1)) <= lim.max_accel_xy_m_s2 + 1e-6
    assert max(p[0] for p, _ in trace) < 6.0 + 0.05
    assert v.position_ned_m[0] == pytest.approx(6.0, abs=0.02)


def test_floor_stops_descent_and_unpowered_vehicle_falls() -> None:
    v = KinematicMulticopter()
    v.motors_on = True
    v.set_target(Target(velocity_ned_m_s=(0.0, 0.0, 1.0)))
    _fly(v, 1.0)
    assert v.position_ned_m[2] == 0.0 and v.on_ground
    v.set_target(Target(position_ned_m=(0.0, 0.0, -3.0)))
    _fly(v, 4.0)
    assert not v.on_ground
    v.motors_on = False
    _fly(v, 2.0)
    assert v.position_ned_m[2] == 0.0 and v.velocity_ned_m_s == (0.0, 0.0, 0.0)


def test_yaw_rate_limited_and_wraps() -> None:
    lim = VehicleLimits(max_yaw_rate_rad_s=math.radians(45))
    v = KinematicMulticopter(lim, position_ned_m=(0.0, 0.0, -1.0), yaw_rad=math.radians(170))
    v.motors_on = True
    v.set_target(Target(position_ned_m=(0.0, 0.0, -1.0), yaw_rad=math.radians(-170)))
    v.step(DT)
    assert abs(v.state().yaw_rate_rad_s) <= lim.max_yaw_rate_rad_s + 1e-9
    _fly(v, 2.0)
    # the short way round through 180 degrees
    assert math.degrees(v.yaw_rad) == pytest.approx(-170, abs=0.5)


def test_nan_axis_leaves_it_to_velocity() -> None:
    v = KinematicMulticopter(position_ned_m=(0.0, 0.0, -2.0))
    v.motors_on = True
    v.set_target(Target(position_ned_m=(1.0, 1.0, math.nan), velocity_ned_m_s=(0, 0, 0.5)))
    _fly(v, 6.0)
    n, e, d = v.position_ned_m
    assert (n, e) == pytest.approx((1.0, 1.0), abs=0.02) and d == 0.0


def test_T_map_body_is_enu_flu() -> None:  # noqa: N802 - frame names
    v = KinematicMulticopter(position_ned_m=(1.0, 2.0, -3.0), yaw_rad=0.0)
    T = v.T_map_body()
    assert T[:3, 3] == pytest.approx([2.0, 1.0, 3.0])  # x east, y north, z up
    assert T[:3, 0] == pytest.approx([0.0, 1.0, 0.0])  # facing north: body x = map +y
    assert T[:3, 2] == pytest.approx([0.0, 0.0, 1.0])  # body z up
    v2 = KinematicMulticopter(yaw_rad=math.pi / 2)  # facing east
    assert v2.T_map_body()[:3, 0] == pytest.approx([1.0, 0.0, 0.0], abs=1e-12)


# --- offboard setpoints --------------------------------------------------------------------------

_mav = mavlink.MAVLink(None, 1, 191)
POS_ONLY = (offboard.IGNORE_VX | offboard.IGNORE_VY | offboard.IGNORE_VZ | offboard.IGNORE_YAW_RATE
            | mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE
            | mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE)
VEL_ONLY = (offboard.IGNORE_PX | offboard.IGNORE_PY | offboard.IGNORE_PZ | offboard.IGNORE_YAW
            | mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE
            | mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE)


def _local(frame: int, mask: int, xyz=(0.0, 0.0, 0.0), vel=(0.0, 0.0, 0.0), yaw=0.0, rate=0.0):
    return _mav.set_position_target_local_ned_encode(0, 1, 1, frame, mask, *xyz, *vel, 0, 0, 0,
                                                     yaw, rate)


def test_local_ned_position_setpoint() -> None:
    t = offboard.target_from_local_ned(_local(mavlink.MAV_FRAME_LOCAL_NED, POS_ONLY, (1, 2, -3),
                                              yaw=0.5), (9, 9, 9), 0.0)
    assert t.position_ned_m == (1, 2, -3) and t.velocity_ned_m_s is None
    assert t.yaw_rad == pytest.approx(0.5) and t.yaw_rate_rad_s is None


def test_body_frames_rotate_by_heading() -> None:
    yaw = math.pi / 2  # facing east
    t = offboard.target_from_local_ned(
        _local(mavlink.MAV_FRAME_BODY_NED, VEL_ONLY, vel=(1.0, 0.0, 0.0)), (0, 0, -1), yaw)
    assert t.velocity_ned_m_s == pytest.approx((0.0, 1.0, 0.0), abs=1e-12)
    t = offboard.target_from_local_ned(
        _local(mavlink.MAV_FRAME_BODY_OFFSET_NED, POS_ONLY, (2.0, 0.0, 0.0)), (1, 1, -1), yaw)
    assert t.position_ned_m == pytest.approx((1.0, 3.0, -1.0), abs=1e-12)


def test_unsupported_setpoints_raise() -> None:
    with pytest.raises(offboard.UnsupportedSetpointError, match="coordinate_frame 12"):
        offboard.target_from_local_ned(_local(12, POS_ONLY), (0, 0, 0), 0.0)
    with pytest.raises(offboard.UnsupportedSetpointError, match="ignores every field"):
        offboard.target_from_local_ned(_local(1, 0xFFF), (0, 0, 0), 0.0)


def test_attitude_target_hover_is_level_and_still() -> None:
    msg = _mav.set_attitude_target_encode(0, 1, 1, 0, [1, 0, 0, 0], 0, 0, 0, 0.5)
    t = offboard.target_from_attitude(msg, 3.0)
    assert t.velocity_ned_m_s == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)
    msg = _mav.set_attitude_target_encode(0, 1, 1, 0, [1, 0, 0, 0], 0, 0, 0, 1.0)
    assert offboard.target_from_attitude(msg, 3.0).velocity_ned_m_s[2] == pytest.approx(-3.0)


# --- parameters ----------------------------------------------------------------------------------

@given(st.integers(-(2**31), 2**31 - 1))
def test_int_params_bytewise_round_trip(value: int) -> None:
    enc = encode_param_value(value, MAV_PARAM_TYPE_INT32)
    assert decode_param_value(enc, MAV_PARAM_TYPE_INT32) == value or math.isnan(enc)


def test_param_store() -> None:
    p = ParamStore({"MIS_TAKEOFF_ALT": 1.2})
    assert p.get("MIS_TAKEOFF_ALT") == pytest.approx(1.2)
    assert p.spec("MIS_TAKEOFF_ALT").param_type == MAV_PARAM_TYPE_REAL32
    assert p.set("COM_OBL_RC_ACT", 3.7) == 4.0
    assert p.name_at(p.index_of("NAV_ACC_RAD")) == "NAV_ACC_RAD" and p.name_at(999) is None
    with pytest.raises(KeyError, match="NOPE"):
        p.set("NOPE", 1)


def test_climb_rate_limit_applies_to_takeoff_targets() -> None:
    v = KinematicMulticopter(VehicleLimits(max_speed_up_m_s=3.0))
    v.motors_on = True
    v.set_target(Target(position_ned_m=(0.0, 0.0, -5.0), speed_up_m_s=1.0))
    trace = _fly(v, 2.0)
    assert min(vel[2] for _, vel in trace) >= -1.0 - 1e-9
    assert v.position_ned_m[2] < -1.5  # it does climb


def test_rtl_goes_to_home_not_the_origin() -> None:
    v = KinematicMulticopter(position_ned_m=(0.0, 0.0, -3.0))
    v.motors_on = True
    params = ParamStore({"RTL_RETURN_ALT": 4.0, "RTL_DESCEND_ALT": 2.0})
    modes: list[FlightMode] = []
    nav = Navigator(v, params, GeoOrigin(), modes.append, lambda s: None, lambda s: None)
    nav.home_ned_m = (5.0, -2.0, 0.0)
    nav.enter(FlightMode.RTL)
    lowest_d = 0.0
    for _ in range(int(40 / DT)):
        v.step(DT)
        nav.tick(v.stamp_s)
        lowest_d = min(lowest_d, v.position_ned_m[2])
        if nav.landed_by_navigator:
            break
    assert nav.landed_by_navigator
    assert v.position_ned_m == pytest.approx((5.0, -2.0, 0.0), abs=0.05)
    assert lowest_d == pytest.approx(-4.0, abs=0.1)  # climbed to RTL_RETURN_ALT first


def test_velocity_loop_gain_trails_a_moving_setpoint_and_overshoots_its_end() -> None:
    """With PX4's velocity loop (MPC_XY_VEL_P_ACC, no acceleration feed-forward) the vehicle
    trails a setpoint that speeds up to 1 m/s and slows to a stop at 1 m/s^2, and is still
    moving when the setpoint has stopped; without it the mock followed exactly."""
    results = {}
    for gain in (None, 1.8):
        v = KinematicMulticopter(position_ned_m=(0.0, 0.0, -1.0))
        v.motors_on = True
        x_sp, speed_sp, end_m = 0.0, 0.0, 3.0
        lags = []
        while x_sp < end_m:
            braking = (end_m - x_sp) <= speed_sp ** 2 / 2.0
            speed_sp = max(0.01, speed_sp - DT) if braking else min(1.0, speed_sp + DT)
            x_sp = min(end_m, x_sp + speed_sp * DT)
            v.set_target(Target(position_ned_m=(x_sp, 0.0, -1.0), velocity_ned_m_s=(speed_sp, 0.0, 0.0),
                                velocity_gain_1_s=gain))
            v.step(DT)
            lags.append(x_sp - v.position_ned_m[0])
        speed_at_end = math.hypot(*v.velocity_ned_m_s[:2])
        v.set_target(Target(position_ned_m=(end_m, 0.0, -1.0), velocity_gain_1_s=gain))
        trace = _fly(v, 4.0)
        results[gain] = (max(lags), speed_at_end, max(p[0] for p, _ in trace) - end_m)
    assert results[None][0] < 0.02 and results[None][1] < 0.05 and results[None][2] < 0.02
    lag_m, speed_m_s, overshoot_m = results[1.8]
    assert 0.2 < lag_m < 0.8 and speed_m_s > 0.2 and overshoot_m > 0.1
    assert v.position_ned_m[0] == pytest.approx(end_m, abs=0.03)  # and it comes back


def test_every_mock_parameter_reads_back_as_the_link_decodes_it() -> None:
    # The mock answers with encode_param_value; our link reads with decode_param_value.
    p = ParamStore()
    for name in (p.name_at(i) for i in range(len(p))):
        assert name is not None
        spec = p.spec(name)
        wire = encode_param_value(p.get(name), spec.param_type)
        assert decode_param_value(wire, spec.param_type) == p.get(name), name
