"""The offboard failsafe state machine, stepped with a fake clock (no sockets, no sleeps)."""

from __future__ import annotations

import dataclasses

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.mavlink.failsafe import OffboardFailsafe, OffboardState, PositionSetpoint
from companion.mavlink.state import LandedState, VehicleState
from companion.px4 import FlightMode

HB_TIMEOUT_S = 3.0
POS_TIMEOUT_S = 0.5


def _vehicle(**changes: object) -> VehicleState:
    base = VehicleState(
        heartbeat_age_s=0.1, armed=True, flight_mode=FlightMode.POSCTL,
        landed_state=LandedState.IN_AIR, position_ned_m=(1.0, 2.0, -1.5),
        velocity_ned_m_s=(0.0, 0.0, 0.0), position_age_s=0.02, attitude_rpy_rad=(0.0, 0.0, 0.3),
        battery_v=16.0, battery_remaining=0.8, home=None, global_position=None,
        autopilot_system_status=4,
    )
    return dataclasses.replace(base, **changes)


def _engaged(now_s: float = 0.0) -> OffboardFailsafe:
    fs = OffboardFailsafe(HB_TIMEOUT_S, POS_TIMEOUT_S)
    fs.set_setpoint(PositionSetpoint((5.0, 0.0, -1.5), yaw_rad=0.0), now_s)
    fs.start_engage(now_s, _vehicle())
    assert fs.step(now_s, _vehicle(), True, True) is not None
    fs.engaged(now_s + 1.0)
    return fs


def test_idle_sends_nothing() -> None:
    fs = OffboardFailsafe(HB_TIMEOUT_S, POS_TIMEOUT_S)
    fs.set_setpoint(PositionSetpoint((1.0, 1.0, -1.0)), 0.0)
    assert fs.step(0.1, _vehicle(), True, True) is None
    assert fs.state is OffboardState.IDLE


def test_engage_without_a_plan_streams_a_hold_at_the_vehicle() -> None:
    fs = OffboardFailsafe(HB_TIMEOUT_S, POS_TIMEOUT_S)
    fs.start_engage(0.0, _vehicle())
    sp = fs.step(0.02, _vehicle(), True, True)
    assert fs.state is OffboardState.WARMUP
    assert sp == PositionSetpoint((1.0, 2.0, -1.5), yaw_rad=0.3)
    fs.engaged(1.1)
    assert fs.step(1.12, _vehicle(flight_mode=FlightMode.OFFBOARD), True, True) == sp
    # The planner's first setpoint (newer than the hold) takes over.
    plan = PositionSetpoint((4.0, 0.0, -2.0), yaw_rad=1.0, velocity_ned_m_s=(0.5, 0.0, 0.0))
    fs.set_setpoint(plan, 1.2)
    assert fs.step(1.22, _vehicle(flight_mode=FlightMode.OFFBOARD), True, True) == plan
    assert fs.state is OffboardState.ACTIVE


def test_active_streams_the_latest_setpoint() -> None:
    fs = _engaged()
    v = _vehicle(flight_mode=FlightMode.OFFBOARD)
    for i in range(5):
        sp = PositionSetpoint((float(i), 0.0, -1.5))
        fs.set_setpoint(sp, 2.0 + i)
        assert fs.step(2.01 + i, v, True, True) == sp
    # No new setpoint: the latest one keeps streaming (never waits for the planner).
    assert fs.step(9.0, v, True, True) == sp


def test_heartbeat_loss_stops_commanding_until_told() -> None:
    fs = _engaged()
    assert fs.step(2.0, _vehicle(flight_mode=FlightMode.OFFBOARD, heartbeat_age_s=3.5), True, True) is None
    assert fs.state is OffboardState.LINK_LOST
    assert "heartbeat lost" in fs.reason
    # The link comes back, still in OFFBOARD: we stay quiet - re-engaging is an explicit decision.
    back = _vehicle(flight_mode=FlightMode.OFFBOARD)
    for t in (3.0, 4.0, 10.0):
        assert fs.step(t, back, True, True) is None
    assert fs.state is OffboardState.LINK_LOST
    fs.start_engage(11.0, back)
    assert fs.step(11.02, back, True, True) is not None
    assert fs.state is OffboardState.WARMUP


def test_never_seen_heartbeat_is_link_loss_during_warmup() -> None:
    fs = OffboardFailsafe(HB_TIMEOUT_S, POS_TIMEOUT_S)
    fs.set_setpoint(PositionSetpoint((0.0, 0.0, -1.0)), 0.0)
    fs.start_engage(0.0, _vehicle())
    assert fs.step(0.1, _vehicle(heartbeat_age_s=None), True, True) is None
    assert fs.state is OffboardState.LINK_LOST


@pytest.mark.parametrize("mode", [FlightMode.POSCTL, FlightMode.HOLD, FlightMode.LAND, None])
def test_pilot_switching_out_of_offboard_makes_us_yield(mode: FlightMode | None) -> None:
    fs = _engaged()
    assert fs.step(2.0, _vehicle(flight_mode=mode), True, True) is None
    assert fs.state is OffboardState.YIELDED
    # Even when the pilot goes back to OFFBOARD we do not grab control by ourselves.
    assert fs.step(3.0, _vehicle(flight_mode=FlightMode.OFFBOARD), True, True) is None
    assert fs.state is OffboardState.YIELDED


def test_our_own_mode_change_is_not_a_takeover() -> None:
    fs = _engaged()
    fs.release_pending = True
    assert fs.step(2.0, _vehicle(flight_mode=FlightMode.HOLD), True, True) is None
    assert fs.state is OffboardState.ACTIVE
    fs.release(2.1, "released to HOLD")
    assert fs.state is OffboardState.IDLE


def test_warmup_ignores_the_current_mode() -> None:
    fs = OffboardFailsafe(HB_TIMEOUT_S, POS_TIMEOUT_S)
    fs.set_setpoint(PositionSetpoint((0.0, 0.0, -1.0)), 0.0)
    fs.start_engage(0.0, _vehicle())
    for i in range(30):  # 1 s at 30 Hz, vehicle still in POSCTL
        assert fs.step(i / 30.0, _vehicle(), True, True) is not None
    assert fs.state is OffboardState.WARMUP


@pytest.mark.parametrize(("pose_fresh", "map_fresh", "what"),
                         [(False, True, "pose"), (True, False, "map"), (False, False, "pose and map")])
def test_stale_inputs_hold_the_current_position(pose_fresh: bool, map_fresh: bool, what: str) -> None:
    fs = _engaged()
    v = _vehicle(flight_mode=FlightMode.OFFBOARD, position_ned_m=(3.0, 1.0, -1.6))
    sp = fs.step(2.0, v, pose_fresh, map_fresh)
    assert fs.state is OffboardState.HOLDING
    assert f"stale {what}" in fs.reason
    assert sp == PositionSetpoint((3.0, 1.0, -1.6), yaw_rad=0.3)
    # The hold is latched: the vehicle drifting does not drag the setpoint along.
    v2 = dataclasses.replace(v, position_ned_m=(3.08, 1.04, -1.6))
    assert fs.step(2.1, v2, pose_fresh, map_fresh) == sp
    # Fresh again, but the planner's last setpoint predates the hold: keep holding.
    assert fs.step(2.2, v2, True, True) == sp
    assert fs.state is OffboardState.HOLDING
    new = PositionSetpoint((6.0, 0.0, -1.5))
    fs.set_setpoint(new, 2.3)
    assert fs.step(2.31, v2, True, True) == new
    assert fs.state is OffboardState.ACTIVE


def test_hold_uses_the_last_setpoint_when_telemetry_position_is_stale_too() -> None:
    fs = _engaged()
    v = _vehicle(flight_mode=FlightMode.OFFBOARD)
    last = fs.step(2.0, v, True, True)
    assert last is not None
    stale = _vehicle(flight_mode=FlightMode.OFFBOARD, position_ned_m=(9.0, 9.0, -9.0), position_age_s=2.0)
    sp = fs.step(2.1, stale, False, True)
    assert sp is not None and sp.position_ned_m == last.position_ned_m


def test_stale_hold_still_yields_and_detects_link_loss() -> None:
    fs = _engaged()
    fs.step(2.0, _vehicle(flight_mode=FlightMode.OFFBOARD), False, True)
    assert fs.state is OffboardState.HOLDING
    assert fs.step(2.1, _vehicle(flight_mode=FlightMode.RTL), False, True) is None
    assert fs.state is OffboardState.YIELDED


def test_setpoints_must_be_finite() -> None:
    with pytest.raises(ValueError, match="non-finite"):
        PositionSetpoint((0.0, float("nan"), -1.0))
    with pytest.raises(ValueError, match="non-finite"):
        PositionSetpoint((0.0, 0.0, -1.0), yaw_rad=float("inf"))


_EVENTS = st.sampled_from(["tick", "hb_lost", "pilot", "stale", "fresh", "engage", "engaged",
                           "setpoint"])


@settings(max_examples=200, deadline=None)
@given(events=st.lists(_EVENTS, min_size=1, max_size=40))
def test_invariants_under_any_event_sequence(events: list[str]) -> None:
    """Whatever happens: quiet without a heartbeat or after a takeover, and never recover alone."""
    fs = OffboardFailsafe(HB_TIMEOUT_S, POS_TIMEOUT_S)
    mode: FlightMode | None = FlightMode.POSCTL
    hb_age = 0.1
    fresh = True
    t = 0.0
    for ev in events:
        t += 0.05
        before = fs.state
        if ev == "hb_lost":
            hb_age = 5.0
        elif ev == "pilot":
            mode = FlightMode.POSCTL
        elif ev == "stale":
            fresh = False
        elif ev == "fresh":
            fresh, hb_age = True, 0.1
        elif ev == "engage":
            fs.start_engage(t, _vehicle(heartbeat_age_s=hb_age, flight_mode=mode))
            before = fs.state
        elif ev == "engaged" and fs.state is OffboardState.WARMUP:
            mode = FlightMode.OFFBOARD
            fs.engaged(t)
            before = fs.state
        elif ev == "setpoint":
            fs.set_setpoint(PositionSetpoint((t, 0.0, -1.0)), t)
        v = _vehicle(heartbeat_age_s=hb_age, flight_mode=mode)
        sp = fs.step(t, v, fresh, fresh)
        if hb_age > HB_TIMEOUT_S:
            assert sp is None
        if before in (OffboardState.YIELDED, OffboardState.LINK_LOST, OffboardState.IDLE):
            assert fs.state is before and sp is None
        if fs.state in (OffboardState.ACTIVE, OffboardState.HOLDING):
            assert mode is FlightMode.OFFBOARD
            assert sp is not None


def test_tracking_monitor_holds_a_vehicle_that_does_not_follow() -> None:
    """On PX4 SITL OFFBOARD was engaged on the ground: the vehicle sat landed while the
    setpoints moved 4 m away, then took off towards them through a desk. A vehicle farther
    than tracking_error_m from its setpoint for tracking_timeout_s is held where it is."""
    fs = OffboardFailsafe(HB_TIMEOUT_S, POS_TIMEOUT_S, tracking_error_m=1.0, tracking_timeout_s=2.0)
    fs.set_setpoint(PositionSetpoint((1.0, 2.0, -1.5)), 0.0)
    fs.start_engage(0.0, _vehicle())
    fs.step(0.0, _vehicle(), True, True)
    fs.engaged(1.0)
    stuck = _vehicle(flight_mode=FlightMode.OFFBOARD, landed_state=LandedState.ON_GROUND,
                     position_ned_m=(1.0, 2.0, 0.0))
    far = PositionSetpoint((5.0, 2.0, -1.5))
    t = 1.0
    while t < 2.9:  # 4 m away: tolerated for less than 2 s
        fs.set_setpoint(far, t)
        assert fs.step(t, stuck, True, True) == far
        t += 0.05
    fs.set_setpoint(far, t)
    fs.step(t, stuck, True, True)
    t += 0.2
    fs.set_setpoint(far, t)
    sp = fs.step(t, stuck, True, True)
    assert fs.state is OffboardState.HOLDING and fs.tracking_fault
    assert sp == PositionSetpoint((1.0, 2.0, 0.0), yaw_rad=0.3)  # held where it is
    # A new plan from where the vehicle is resumes flight and clears the fault.
    near = PositionSetpoint((1.2, 2.0, -0.2))
    fs.set_setpoint(near, t + 0.1)
    assert fs.step(t + 0.1, stuck, True, True) == near
    assert fs.state is OffboardState.ACTIVE and not fs.tracking_fault


def test_tracking_monitor_tolerates_a_vehicle_that_lags_within_the_distance() -> None:
    fs = OffboardFailsafe(HB_TIMEOUT_S, POS_TIMEOUT_S, tracking_error_m=1.0, tracking_timeout_s=2.0)
    fs.set_setpoint(PositionSetpoint((1.0, 2.0, -1.5)), 0.0)
    fs.start_engage(0.0, _vehicle())
    fs.step(0.0, _vehicle(), True, True)
    fs.engaged(1.0)
    for k in range(200):  # 10 s with the setpoint 0.8 m ahead of the vehicle
        t = 1.0 + 0.05 * k
        fs.set_setpoint(PositionSetpoint((1.8, 2.0, -1.5)), t)
        fs.step(t, _vehicle(flight_mode=FlightMode.OFFBOARD), True, True)
    assert fs.state is OffboardState.ACTIVE


def test_a_jump_of_the_position_estimate_holds_where_the_vehicle_now_is() -> None:
    # PX4 resets its position to our vision pose when it comes back after a loss: the
    # setpoints were planned in the old estimate, and flying on to them would be a straight,
    # unplanned line (PX4 SITL: into a chair 0.5 m away).
    fs = _engaged()
    v = _vehicle(flight_mode=FlightMode.OFFBOARD, position_ned_m=(3.0, 1.0, -1.6))
    assert fs.step(2.0, v, True, True) == PositionSetpoint((5.0, 0.0, -1.5), yaw_rad=0.0)
    jumped = dataclasses.replace(v, position_ned_m=(3.4, 1.3, -1.6))
    sp = fs.step(2.05, jumped, True, True)
    assert fs.state is OffboardState.HOLDING and fs.position_reset
    assert "jumped 0.50 m" in fs.reason
    assert sp == PositionSetpoint((3.4, 1.3, -1.6), yaw_rad=0.3)
    # The leg re-plans once; the new leg, started while the hold lasts, is not told again
    # (gd12 room 2 re-planned twice for one jump).
    assert fs.take_position_reset() and not fs.take_position_reset()
    assert fs.state is OffboardState.HOLDING
    # A plan made after the jump takes over.
    new = PositionSetpoint((6.0, 0.0, -1.5))
    fs.set_setpoint(new, 2.1)
    assert fs.step(2.12, jumped, True, True) == new
    assert fs.state is OffboardState.ACTIVE and not fs.position_reset


def test_motion_its_velocity_explains_is_no_jump() -> None:
    fs = _engaged()
    for k in range(40):  # 1.2 m/s along north, a report every 50 ms
        v = _vehicle(flight_mode=FlightMode.OFFBOARD, position_ned_m=(1.0 + 0.06 * k, 2.0, -1.5),
                     velocity_ned_m_s=(1.2, 0.0, 0.0))
        fs.step(2.0 + 0.05 * k, v, True, True)
        assert fs.state is OffboardState.ACTIVE


def test_reports_queued_behind_a_stall_are_no_jump() -> None:
    # A stall of our loop queues the autopilot's reports, which then arrive together: timed by
    # arrival, 0.2 m flown in 0.1 s at 2 m/s would read as a jump 10 ms apart, and the
    # vehicle would stop to hold mid-leg (a CI run's re-plan flight under load).
    fs = _engaged()
    fly = {"flight_mode": FlightMode.OFFBOARD, "velocity_ned_m_s": (2.0, 0.0, 0.0), "position_age_s": 0.0}
    fs.step(2.0, _vehicle(**fly, position_ned_m=(1.0, 2.0, -1.5), position_boot_s=10.0), True, True)
    fs.step(2.01, _vehicle(**fly, position_ned_m=(1.2, 2.0, -1.5), position_boot_s=10.1), True, True)
    assert fs.state is OffboardState.ACTIVE and not fs.position_reset
    # A real reset between two reports 33 ms apart is still one.
    fs.step(2.05, _vehicle(**fly, position_ned_m=(1.7, 2.0, -1.5), position_boot_s=10.133), True, True)
    assert fs.state is OffboardState.HOLDING and fs.position_reset


def test_a_jump_during_a_hold_moves_the_hold_to_where_the_vehicle_now_is() -> None:
    fs = _engaged()
    v = _vehicle(flight_mode=FlightMode.OFFBOARD, position_ned_m=(3.0, 1.0, -1.6))
    held = fs.step(2.0, v, False, True)
    assert held == PositionSetpoint((3.0, 1.0, -1.6), yaw_rad=0.3)
    jumped = dataclasses.replace(v, position_ned_m=(2.6, 1.0, -1.6))
    assert fs.step(2.05, jumped, False, True) == PositionSetpoint((2.6, 1.0, -1.6), yaw_rad=0.3)
    assert fs.state is OffboardState.HOLDING and fs.position_reset
