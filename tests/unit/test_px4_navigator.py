"""The mock autopilot's navigator flying missions in simulated time (no sockets, no clock)."""

from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20 import common as mavlink

from companion.geo import GeoOrigin
from companion.missions import MissionItemInt
from companion.px4 import FlightMode
from companion.sim.autopilot.navigator import MissionState, Navigator
from companion.sim.autopilot.params import ParamStore
from companion.sim.autopilot.vehicle import KinematicMulticopter, Target

HOME = GeoOrigin()
DT = 0.01


def _wp(seq: int, n: float, e: float, alt: float, cmd: int = mavlink.MAV_CMD_NAV_WAYPOINT,
        p1: float = 0.0) -> MissionItemInt:
    lat, lon, _ = HOME.to_global(n, e, 0.0)
    return MissionItemInt(seq, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, cmd, int(seq == 0), 1,
                          p1, 0.3, 0.0, math.nan, round(lat * 1e7), round(lon * 1e7), alt)


def _do(seq: int, cmd: int, p1: float = 0.0, p2: float = 0.0) -> MissionItemInt:
    return MissionItemInt(seq, mavlink.MAV_FRAME_MISSION, cmd, 0, 1, p1, p2, -1.0, 0.0, 0, 0,
                          math.nan)


class _Sim:
    def __init__(self, items: list[MissionItemInt]) -> None:
        self.vehicle = KinematicMulticopter()
        self.vehicle.motors_on = True
        self.reached: list[tuple[int, float]] = []
        self.modes: list[FlightMode] = []
        self.nav = Navigator(self.vehicle, ParamStore({"MIS_TAKEOFF_ALT": 1.0}), HOME,
                             self.modes.append, lambda s: self.reached.append(
                                 (s, self.vehicle.stamp_s)), lambda s: None)
        self.nav.set_mission(items)
        self.max_speed = 0.0
        self.max_alt = 0.0

    def run(self, seconds: float) -> None:
        for _ in range(int(seconds / DT)):
            self.vehicle.step(DT)
            self.nav.tick(self.vehicle.stamp_s)
            vn, ve, _ = self.vehicle.velocity_ned_m_s
            self.max_speed = max(self.max_speed, math.hypot(vn, ve))
            self.max_alt = max(self.max_alt, -self.vehicle.position_ned_m[2])
            if self.nav.mission_state is MissionState.COMPLETE and self.nav.landed_by_navigator:
                return


def test_jump_loiter_speed_and_landing() -> None:
    items = [
        _do(0, mavlink.MAV_CMD_DO_CHANGE_SPEED, 1.0, 1.5),
        _wp(1, 2.0, 0.0, 2.0),
        _wp(2, 2.0, 2.0, 2.0, mavlink.MAV_CMD_NAV_LOITER_TIME, p1=1.5),
        _do(3, mavlink.MAV_CMD_DO_JUMP, 1.0, 1.0),  # back to item 1, once
        _wp(4, 0.0, 0.0, 2.0),
        _wp(5, 0.0, 0.0, 0.0, mavlink.MAV_CMD_NAV_LAND),
    ]
    sim = _Sim(items)
    sim.nav.enter(FlightMode.MISSION)
    sim.run(120.0)
    assert [s for s, _ in sim.reached] == [1, 2, 1, 2, 4, 5]
    # LOITER_TIME: reached on arrival, then 1.5 s of hold before the next item is flown.
    t_loiter = sim.reached[1][1]
    t_next = sim.reached[2][1]
    assert t_next - t_loiter > 1.5
    assert sim.max_speed <= 1.5 + 1e-6  # DO_CHANGE_SPEED applies to the whole mission
    assert sim.nav.mission_state is MissionState.COMPLETE and sim.vehicle.on_ground
    assert sim.vehicle.position_ned_m == pytest.approx((0.0, 0.0, 0.0), abs=0.35)


def test_mission_from_the_ground_takes_off_first() -> None:
    sim = _Sim([_wp(0, 3.0, 0.0, 0.5)])
    sim.nav.enter(FlightMode.MISSION)
    sim.run(30.0)
    # MIS_TAKEOFF_ALT (1 m) is above the first waypoint (0.5 m): climb towards it first
    # (to within the 0.2 m vertical acceptance), then fly to the waypoint.
    assert 0.75 < sim.max_alt < 1.05
    assert sim.nav.mission_state is MissionState.COMPLETE
    assert sim.vehicle.position_ned_m == pytest.approx((3.0, 0.0, -0.5), abs=0.1)


def test_takeoff_mode_ends_in_hold_at_altitude() -> None:
    sim = _Sim([])
    sim.nav.enter(FlightMode.TAKEOFF, takeoff_alt_m=2.0)
    sim.run(5.0)
    assert sim.modes == [FlightMode.HOLD]
    assert sim.vehicle.position_ned_m[2] == pytest.approx(-2.0, abs=0.05)


@pytest.mark.parametrize(("brake_m_s2", "landed_from_entry_m"), [(0.5, 0.9), (0.0, 0.0)])
def test_land_engaged_at_speed_lands_where_the_brake_stops(brake_m_s2: float, landed_from_entry_m: float) -> None:
    """PX4 SITL, handed to Land at 0.95 m/s, braked gently and landed 0.9 m on; the naive
    mock came back to where Land was engaged."""
    vehicle = KinematicMulticopter(position_ned_m=(0.0, 0.0, -2.0))
    vehicle.motors_on = True
    nav = Navigator(vehicle, ParamStore(), HOME, lambda m: None, lambda s: None, lambda s: None,
                    land_brake_accel_m_s2=brake_m_s2)
    nav.enter(FlightMode.HOLD, hold_at_ned_m=(0.0, 0.0, -2.0))
    vehicle.set_target(Target(velocity_ned_m_s=(0.95, 0.0, 0.0)))
    for _ in range(int(2.0 / DT)):
        vehicle.step(DT)
    entry_n = vehicle.position_ned_m[0]
    assert vehicle.velocity_ned_m_s[0] == pytest.approx(0.95, abs=0.01)
    nav.enter(FlightMode.LAND)
    for _ in range(int(8.0 / DT)):
        vehicle.step(DT)
        nav.tick(vehicle.stamp_s)
    assert vehicle.on_ground
    assert vehicle.position_ned_m[0] - entry_n == pytest.approx(landed_from_entry_m, abs=0.1)
