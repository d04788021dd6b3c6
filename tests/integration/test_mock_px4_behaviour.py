"""The mock autopilot behaves like real PX4 where a naive autopilot would not.

One test per behaviour of :class:`~companion.sim.autopilot.behaviour.Px4Behaviour`, each also
checking that its switch turns it off. Measured PX4 SITL behaviour is listed in
``../shared/px4-sitl/README.md``.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import AsyncIterator
from dataclasses import replace
from typing import Any

import pytest
from pymavlink.dialects.v20 import common as mavlink
from raw_mavlink_client import RawClient

from companion import px4
from companion.px4 import FlightMode
from companion.sim.autopilot import MockAutopilot
from companion.sim.autopilot.behaviour import Px4Behaviour

pytestmark = [pytest.mark.asyncio, pytest.mark.timeout(60)]

NAN = math.nan
ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
#: Brisk take-off and landing keep these short; the behaviours under test are unchanged.
PARAMS = {"MPC_TKO_SPEED": 3.0, "MPC_LAND_SPEED": 1.5}
PX4 = Px4Behaviour()


@contextlib.asynccontextmanager
async def mock(behaviour: Px4Behaviour = PX4, **params: float) -> AsyncIterator[tuple[MockAutopilot, RawClient]]:
    """The mock with ``behaviour`` and a raw client reading everything it sends."""
    client = RawClient()
    async with MockAutopilot(local_port=0, remote_ports=[client.port], params={**PARAMS, **params},
                             behaviour=behaviour) as ap:
        client.ap_addr = ("127.0.0.1", ap.local_port)

        async def keep_reading() -> None:
            while True:
                client._drain()
                await asyncio.sleep(0.01)

        reader = asyncio.create_task(keep_reading())
        try:
            yield ap, client
        finally:
            reader.cancel()
    client.close()


def _position_setpoint(c: RawClient, n: float, e: float, d: float, yaw: float = 0.0) -> Any:
    mask = (mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE
            | mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE
            | mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE
            | mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE)
    return c.mav.set_position_target_local_ned_encode(0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, mask,
                                                      n, e, d, 0, 0, 0, 0, 0, 0, yaw, 0)


async def _take_off(ap: MockAutopilot, c: RawClient, alt_m: float = 2.5) -> None:
    await c.wait_ready()
    assert await c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == ACCEPTED
    assert await c.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, NAN, NAN, NAN,
                           ap.home.alt_m + alt_m) == ACCEPTED
    await ap.wait_until(lambda: ap.mode is FlightMode.HOLD and ap.position_ned_m[2] < -(alt_m - 0.2),
                        15.0, "take-off")


@contextlib.asynccontextmanager
async def streaming(c: RawClient, n: float, e: float, d: float, period_s: float = 0.05) -> AsyncIterator[None]:
    """Stream one position setpoint (reported frame) while the block runs."""

    async def stream() -> None:
        while True:
            c.send(_position_setpoint(c, n, e, d))
            await asyncio.sleep(period_s)

    task = asyncio.create_task(stream())
    await asyncio.sleep(0.2)  # PX4 needs the stream before it accepts Offboard
    try:
        yield
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


async def test_local_origin_below_the_floor() -> None:
    async with mock() as (ap, c):
        await c.wait_ready()
        pos = await c.recv("LOCAL_POSITION_NED")
        assert pos.z == pytest.approx(-0.86, abs=0.01)
        home = await c.recv("HOME_POSITION", timeout_s=5.0)
        assert home.z == pytest.approx(-0.86, abs=0.01)
        assert home.altitude == pytest.approx(ap.home.alt_m * 1000, abs=10)  # the floor, AMSL
        origin_since = c.mark()
        assert await c.command(mavlink.MAV_CMD_REQUEST_MESSAGE,
                               mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN) == ACCEPTED
        origin = await c.recv("GPS_GLOBAL_ORIGIN", since=origin_since)
        assert origin.altitude == pytest.approx((ap.home.alt_m - 0.86) * 1000, abs=10)
        # The truth stays on the floor.
        assert ap.position_ned_m[2] == 0.0 and ap.state().position_ned_m[2] == 0.0
        await _take_off(ap, c)
        # A setpoint at local z -2.86 is 2 m above the floor.
        async with streaming(c, 1.0, 0.0, -2.86):
            await asyncio.sleep(0.3)
            assert await c.command(mavlink.MAV_CMD_DO_SET_MODE,
                                   *px4.set_mode_params(FlightMode.OFFBOARD)) == ACCEPTED
            await ap.wait_until(lambda: math.dist(ap.position_ned_m, (1.0, 0.0, -2.0)) < 0.15, 10.0,
                                "setpoint reached")
            now = c.mark()
            pos = await c.recv("LOCAL_POSITION_NED", since=now)
            assert pos.z == pytest.approx(-2.86, abs=0.15)
            rel = await c.recv("GLOBAL_POSITION_INT", since=now)
            assert rel.relative_alt == pytest.approx(2000, abs=150)
    async with mock(replace(PX4, floor_z_ned_m=0.0)) as (ap, c):
        pos = await c.recv("LOCAL_POSITION_NED")
        assert pos.z == pytest.approx(0.0, abs=0.01)


async def test_arming_waits_for_readiness() -> None:
    async with mock() as (ap, c):
        status = await c.recv("SYS_STATUS")
        assert not status.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK
        assert await c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == \
            mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        await c.recv("STATUSTEXT", since=0)
        await asyncio.sleep(0.1)
        assert c.status_texts() == ["Arming denied: Resolve system health failures first"]
        assert await c.command(mavlink.MAV_CMD_REQUEST_MESSAGE,
                               mavlink.MAVLINK_MSG_ID_HOME_POSITION) == mavlink.MAV_RESULT_FAILED
        assert c.count("HOME_POSITION") == 0 and not ap.armed
        ready = await c.recv("STATUSTEXT", 5.0, since=0, pred=lambda m: m.text == "Ready for takeoff!")
        assert ready.severity == mavlink.MAV_SEVERITY_INFO
        assert ap.now_s() >= PX4.ready_after_s
        await c.recv("HOME_POSITION", timeout_s=3.0, since=0)
        await c.wait_ready(1.0)
        assert await c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == ACCEPTED
    async with mock(replace(PX4, ready_after_s=0.0)) as (ap, c):
        assert await c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == ACCEPTED


async def _offboard_during_takeoff(behaviour: Px4Behaviour) -> MockAutopilot:
    async with mock(behaviour) as (ap, c):
        await c.wait_ready()
        assert await c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == ACCEPTED
        home = await c.recv("HOME_POSITION", timeout_s=5.0)
        async with streaming(c, 2.0, 0.0, home.z - 1.0):
            assert await c.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, NAN, NAN, NAN,
                                   ap.home.alt_m + 2.5) == ACCEPTED
            await ap.wait_until(lambda: ap.position_ned_m[2] < -0.5, 5.0, "climbing")
            assert ap.mode is FlightMode.TAKEOFF
            assert await c.command(mavlink.MAV_CMD_DO_SET_MODE,
                                   *px4.set_mode_params(FlightMode.OFFBOARD)) == ACCEPTED
            # Until the take-off is over, however slowly a loaded machine climbs, then a while
            # for a request that was kept to show.
            await ap.wait_until(lambda: ap.mode is not FlightMode.TAKEOFF, 15.0, "take-off over")
            await asyncio.sleep(0.5)
            return ap
    raise AssertionError("unreachable")


async def test_offboard_requested_during_takeoff_ends_in_hold() -> None:
    ap = await _offboard_during_takeoff(PX4)
    assert ap.mode is FlightMode.HOLD
    assert [m for _t, m in ap.mode_changes] == [FlightMode.TAKEOFF, FlightMode.HOLD]
    n, e, d = ap.position_ned_m
    assert math.hypot(n, e) < 0.1 and d == pytest.approx(-2.5, abs=0.15)
    ap = await _offboard_during_takeoff(replace(PX4, offboard_during_takeoff_dropped=False))
    assert ap.mode is FlightMode.OFFBOARD


async def test_mode_kept_after_landing_and_rearm_refused_until_changed() -> None:
    denial = "Arming denied: Resolve system health failures first"
    async with mock(COM_DISARM_LAND=0.5) as (ap, c):
        await c.wait_ready()
        # Offboard while disarmed, without setpoints: accepted; the next arm is refused.
        offboard = px4.set_mode_params(FlightMode.OFFBOARD)
        assert await c.command(mavlink.MAV_CMD_DO_SET_MODE, *offboard) == ACCEPTED
        hb = await c.recv("HEARTBEAT", timeout_s=2.0)
        assert px4.decode_heartbeat(hb.base_mode, hb.custom_mode).mode is FlightMode.OFFBOARD
        assert await c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == \
            mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        assert c.status_texts()[-1] == denial
        hold = px4.set_mode_params(FlightMode.HOLD)
        assert await c.command(mavlink.MAV_CMD_DO_SET_MODE, *hold) == ACCEPTED
        await _take_off(ap, c)
        home = await c.recv("HOME_POSITION", timeout_s=5.0)
        # Land in offboard: the vehicle disarms and stays in Offboard.
        async with streaming(c, 0.0, 0.0, home.z + 0.5):
            assert await c.command(mavlink.MAV_CMD_DO_SET_MODE, *offboard) == ACCEPTED
            await ap.wait_until(lambda: not ap.armed, 15.0, "offboard landing and disarm")
        assert ap.mode is FlightMode.OFFBOARD
        assert c.status_texts()[-2:] == ["Landing detected", "Disarmed by landing"]
        await asyncio.sleep(1.2)  # the setpoint stream is gone
        assert await c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == \
            mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        assert await c.command(mavlink.MAV_CMD_DO_SET_MODE, *hold) == ACCEPTED
        # Land mode after Offboard: back in Offboard after the disarm, not Hold.
        await _take_off(ap, c)
        async with streaming(c, 0.0, 0.0, home.z - 2.5):
            assert await c.command(mavlink.MAV_CMD_DO_SET_MODE, *offboard) == ACCEPTED
            assert await c.command(mavlink.MAV_CMD_NAV_LAND) == ACCEPTED
            await ap.wait_until(lambda: not ap.armed, 15.0, "land and disarm")
            assert ap.mode is FlightMode.OFFBOARD
    async with mock(replace(PX4, mode_after_disarm=False), COM_DISARM_LAND=0.5) as (ap, c):
        await c.wait_ready()
        assert await c.command(mavlink.MAV_CMD_DO_SET_MODE, *offboard) == \
            mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        await _take_off(ap, c)
        home = await c.recv("HOME_POSITION", timeout_s=5.0)
        async with streaming(c, 0.0, 0.0, home.z - 2.5):
            assert await c.command(mavlink.MAV_CMD_DO_SET_MODE, *offboard) == ACCEPTED
            assert await c.command(mavlink.MAV_CMD_NAV_LAND) == ACCEPTED
            await ap.wait_until(lambda: not ap.armed, 15.0, "land and disarm")
            await ap.wait_until(lambda: ap.mode is FlightMode.HOLD, 1.0, "naive Hold after landing")


async def _heartbeats_around_mode_changes(behaviour: Px4Behaviour) -> tuple[int, float]:
    """(heartbeats in 1.5 s with 5 mode changes, seconds from the first change to a heartbeat
    showing it)."""
    async with mock(behaviour) as (ap, c):
        await c.recv("HEARTBEAT")
        await asyncio.sleep(0.1)
        since = c.mark()
        t0 = asyncio.get_running_loop().time()
        modes = [FlightMode.POSCTL, FlightMode.HOLD, FlightMode.POSCTL, FlightMode.HOLD, FlightMode.POSCTL]
        for mode in modes:
            assert await c.command(mavlink.MAV_CMD_DO_SET_MODE, *px4.set_mode_params(mode)) == ACCEPTED
        await c.recv("HEARTBEAT", 2.0, since=since, pred=lambda m: px4.decode_heartbeat(
            m.base_mode, m.custom_mode).mode is FlightMode.POSCTL)
        seen_s = asyncio.get_running_loop().time() - t0
        await asyncio.sleep(1.5 - (asyncio.get_running_loop().time() - t0))
        c._drain()
        return sum(1 for m in c.log[since:] if m.get_type() == "HEARTBEAT"), seen_s


async def test_heartbeat_only_at_1_hz() -> None:
    count, _ = await _heartbeats_around_mode_changes(PX4)
    assert count <= 2  # 1 Hz: a change waits for the next one
    count, seen_s = await _heartbeats_around_mode_changes(replace(PX4, heartbeat_on_change=True))
    assert count >= 6 and seen_s < 0.5


async def _clock_rate(behaviour: Px4Behaviour) -> tuple[float, float]:
    """(rate of the mock's TIMESYNC answers, rate of its own TIMESYNC requests) against
    ``time.monotonic`` over 3 s."""

    async with mock(behaviour) as (ap, c):
        samples = []
        for _ in range(2):
            since = c.mark()
            t_send = time.monotonic()
            c.send(c.mav.timesync_encode(0, 12345))
            answer = await c.recv("TIMESYNC", since=since, pred=lambda m: m.ts1 == 12345 and m.tc1 != 0)
            t_answer = 0.5 * (t_send + time.monotonic())
            request = await c.recv("TIMESYNC", since=since, pred=lambda m: m.tc1 == 0)
            samples.append((t_answer, answer.tc1 * 1e-9, request.ts1 * 1e-9))
            if len(samples) == 1:
                await asyncio.sleep(3.0)
        (w0, a0, r0), (w1, a1, r1) = samples
        return (a1 - a0) / (w1 - w0), (r1 - r0) / (w1 - w0)


async def test_clock_drift() -> None:
    answers, requests = await _clock_rate(replace(PX4, clock_rate=1.01))
    assert answers == pytest.approx(1.01, abs=0.004)
    assert requests == pytest.approx(1.01, abs=0.04)  # stamped at a 10 Hz tick
    answers, _ = await _clock_rate(PX4)
    assert answers == pytest.approx(1.0, abs=0.004)


async def _offboard_loss(behaviour: Px4Behaviour) -> tuple[MockAutopilot, list[str]]:
    async with mock(behaviour, COM_DISARM_LAND=0.5) as (ap, c):
        await _take_off(ap, c)
        home = await c.recv("HOME_POSITION", timeout_s=5.0)
        async with streaming(c, 0.0, 0.0, home.z - 2.5):
            assert await c.command(mavlink.MAV_CMD_DO_SET_MODE,
                                   *px4.set_mode_params(FlightMode.OFFBOARD)) == ACCEPTED
            await asyncio.sleep(0.5)
        await ap.wait_until(lambda: bool(ap.failsafes), 2.0, "offboard loss failsafe")
        if behaviour.offboard_loss_px4_actions:
            await ap.wait_until(lambda: not ap.armed, 8.0, "landed and disarmed")
        else:
            await asyncio.sleep(1.0)
        return ap, c.status_texts()


async def test_offboard_loss_ends_in_position_mode_landing() -> None:
    ap, texts = await _offboard_loss(PX4)
    assert ap.failsafes[-1].action is FlightMode.POSCTL
    assert FlightMode.POSCTL in [m for _t, m in ap.mode_changes]
    assert texts[-3:] == ["Failsafe: offboard signal lost, Position", "Landing detected", "Disarmed by landing"]
    assert not ap.armed and ap.position_ned_m[2] == 0.0
    assert ap.mode is FlightMode.OFFBOARD  # disarmed: back to the mode the user chose
    ap, texts = await _offboard_loss(replace(PX4, offboard_loss_px4_actions=False))
    assert ap.failsafes[-1].action is FlightMode.HOLD and ap.mode is FlightMode.HOLD
    assert ap.armed and ap.in_air


async def _armed_on_the_ground(**params: float) -> tuple[float | None, list[str]]:
    """Seconds from arming to the auto-disarm (None: still armed after 11 s), the texts."""
    async with mock(**params) as (ap, c):
        await c.wait_ready()
        assert await c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == ACCEPTED
        armed_at = ap.now_s()
        with contextlib.suppress(TimeoutError):
            await ap.wait_until(lambda: not ap.armed, 11.0, "preflight auto-disarm")
        return (None if ap.armed else ap.now_s() - armed_at), c.status_texts()


async def test_preflight_auto_disarm_after_10_s() -> None:
    (default_s, texts), (off_s, _) = await asyncio.gather(_armed_on_the_ground(),
                                                          _armed_on_the_ground(COM_DISARM_PRFLT=-1.0))
    assert MockAutopilot(local_port=0).params.get("COM_DISARM_PRFLT") == 10.0  # PX4's default
    assert default_s == pytest.approx(10.0, abs=0.3)
    assert texts[-1] == "Disarmed by auto preflight disarming"
    assert off_s is None


async def _hover(behaviour: Px4Behaviour) -> tuple[float, float, float]:
    """(seconds from receiving a setpoint to the controller flying it, max and std of the
    horizontal distance from the setpoint over 3 s of hover)."""
    async with mock(behaviour) as (ap, c):
        await _take_off(ap, c)
        home = await c.recv("HOME_POSITION", timeout_s=5.0)
        async with streaming(c, 0.0, 0.0, home.z - 2.5, period_s=0.1):
            assert await c.command(mavlink.MAV_CMD_DO_SET_MODE,
                                   *px4.set_mode_params(FlightMode.OFFBOARD)) == ACCEPTED
            await asyncio.sleep(0.5)
        c.send(_position_setpoint(c, 1.0, 0.0, home.z - 2.5))
        for _ in range(1000):  # poll finely: the lag is the measurement
            if ap.vehicle.target.position_ned_m[0] == 1.0:
                break
            await asyncio.sleep(0.002)
        lag_s = ap.now_s() - ap.setpoints[-1].stamp_s
        async with streaming(c, 1.0, 0.0, home.z - 2.5, period_s=0.1):
            await ap.wait_until(lambda: math.hypot(ap.position_ned_m[0] - 1.0, ap.position_ned_m[1]) < 0.1,
                                10.0, "setpoint reached")
            await asyncio.sleep(3.0)  # the approach has settled
            errors = []
            for _ in range(60):
                n, e, _d = ap.position_ned_m
                errors.append(math.hypot(n - 1.0, e))
                await asyncio.sleep(0.05)
        mean = sum(errors) / len(errors)
        std = math.sqrt(sum((x - mean) ** 2 for x in errors) / len(errors))
        return lag_s, max(errors), std


async def test_tracking_lags_and_wobbles() -> None:
    lag_s, worst_m, std_m = await _hover(PX4)
    assert lag_s >= PX4.tracking_delay_s - 0.011  # one physics tick
    assert 0.003 < worst_m < 0.1 and std_m > 0.001
    lag_s, worst_m, _ = await _hover(replace(PX4, tracking_delay_s=0.0, wobble_m=0.0, velocity_loop_lag=False))
    assert lag_s < 0.05 and worst_m < 0.002


async def _upload_items(c: RawClient, items: list[tuple[int, float, float, float]]) -> int:
    """Upload ``(command, lat_deg, lon_deg, relative alt m)`` items; the MISSION_ACK type."""
    since = c.mark()
    c.send(c.mav.mission_count_encode(1, 1, len(items), 0))
    for _ in items:
        req = await c.recv("MISSION_REQUEST_INT", since=since)
        since = c.mark()
        cmd, lat, lon, alt = items[req.seq]
        c.send(c.mav.mission_item_int_encode(
            1, 1, req.seq, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, cmd, 0, 1, 0, 0, 0, NAN,
            round(lat * 1e7), round(lon * 1e7), alt, 0))
    return int((await c.recv("MISSION_ACK", since=since)).type)


async def _fly_mission_with_position_free_steps(behaviour: Px4Behaviour) -> tuple[MockAutopilot, list[str]]:
    async with mock(behaviour, NAV_ACC_RAD=0.3) as (ap, c):
        await c.wait_ready()
        lat, lon, _ = ap.home.to_global(2.0, 0.0, 0.0)
        items = [(mavlink.MAV_CMD_NAV_TAKEOFF, 0.0, 0.0, 2.0), (mavlink.MAV_CMD_NAV_WAYPOINT, lat, lon, 2.0),
                 (mavlink.MAV_CMD_NAV_LAND, 0.0, 0.0, 0.0)]
        assert await _upload_items(c, items) == mavlink.MAV_MISSION_ACCEPTED
        assert await c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == ACCEPTED
        assert await c.command(mavlink.MAV_CMD_MISSION_START, 0, 0) == ACCEPTED
        with contextlib.suppress(TimeoutError):
            await ap.wait_until(lambda: ap.position_ned_m[0] < -5.0 or not ap.armed, 20.0,
                                "heading south or landed")
        return ap, c.status_texts()


async def test_mission_items_at_0_0_are_flown_to_0_0() -> None:
    ap, texts = await _fly_mission_with_position_free_steps(PX4)
    home_to_null_island_m = math.hypot(*ap.home.to_ned(0.0, 0.0, 0.0)[:2])
    warning = next(t for t in texts if t.startswith("First waypoint far away from home"))
    assert warning == f"First waypoint far away from home: {home_to_null_island_m:.0f}m. Correct mission loaded?"
    n, e, d = ap.position_ned_m
    assert n < -5.0 and e < 0.0 and d < -1.5  # climbed, then south-west towards 0/0
    assert ap.armed and ap.reached_items == []
    ap, texts = await _fly_mission_with_position_free_steps(replace(PX4, null_island_items=False))
    assert not any(t.startswith("First waypoint") for t in texts)
    assert ap.reached_items == [0, 1, 2] and math.hypot(ap.position_ned_m[0] - 2.0, ap.position_ned_m[1]) < 0.5


@pytest.mark.parametrize("sinks", [True, False])
async def test_hold_sinks_under_a_creeping_height_estimate_that_the_range_finder_shows(sinks: bool) -> None:
    """PX4's Hold flies its height estimate, which creeps away from the floor: the vehicle
    sinks while LOCAL_POSITION_NED holds its height; the downward range finder shows the truth."""
    behaviour = replace(PX4, hold_sink_m_s=0.5 if sinks else 0.0, hold_sink_max_m=0.3)
    async with mock(behaviour) as (ap, c):
        await _take_off(ap, c, alt_m=1.5)
        await asyncio.sleep(1.5)  # past the cap (0.6 s) and the vehicle's catching up
        lp = await c.recv("LOCAL_POSITION_NED")
        rng = await c.recv("DISTANCE_SENSOR")
        true_height_m = -ap.position_ned_m[2]
        reported_height_m = behaviour.floor_z_ned_m - lp.z
        assert rng.orientation == mavlink.MAV_SENSOR_ROTATION_PITCH_270
        assert rng.current_distance / 100.0 == pytest.approx(true_height_m, abs=0.02)
        if sinks:
            assert reported_height_m - true_height_m == pytest.approx(0.3, abs=0.02)
            assert true_height_m == pytest.approx(1.5 - 0.3, abs=0.05)
            # Back on the ground the estimate is true again.
            assert await c.command(mavlink.MAV_CMD_NAV_LAND) == ACCEPTED
            await ap.wait_until(lambda: not ap.in_air and ap.height_error_m == 0.0, 20.0,
                                "landed with the estimate true again")
        else:
            assert reported_height_m == pytest.approx(true_height_m, abs=0.02)
            assert true_height_m == pytest.approx(1.5, abs=0.05)
