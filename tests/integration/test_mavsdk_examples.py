"""Four official MAVSDK-Python examples against the mock autopilot, through the real MAVSDK.

``do_orbit``, ``highres_imu``, ``failure_injection`` and ``follow_me`` (MAVSDK-Python
``examples/``) need more of PX4 than take-off and missions: MAV_CMD_DO_ORBIT, HIGHRES_IMU at a
requested rate, SYS_FAILURE_EN and MAV_CMD_INJECT_FAILURE, the FLW_TGT_* parameters with
FOLLOW_TARGET in Follow Target mode. Each test makes the example's calls in its order with
the native binding (``mavsdk`` 4.x), its waits shortened and its heights indoor-sized, and
checks that the vehicle did what the example asks.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import socket
from collections.abc import AsyncIterator
from typing import Any

import pytest
from mavsdk.asyncio.plugins.failure import FailureAsync
from mavsdk.asyncio.plugins.follow_me import FollowMeAsync
from mavsdk.asyncio.plugins.param import ParamAsync
from mavsdk.plugins.action import OrbitYawBehavior
from mavsdk.plugins.failure import FailureError, FailureType, FailureUnit
from mavsdk.plugins.follow_me import Config, TargetLocation
from mavsdk.plugins.telemetry import FixType
from mavsdk.plugins.telemetry import FlightMode as SdkFlightMode

from companion.mavsdk_client import MavsdkClient
from companion.px4 import FlightMode
from companion.sim.autopilot import MockAutopilot

pytestmark = [pytest.mark.asyncio, pytest.mark.timeout(120)]

#: Brisk take-off and landing keep these short; the behaviour under test is unchanged.
PARAMS = {"MPC_TKO_SPEED": 3.0, "MPC_LAND_SPEED": 1.5, "MIS_TAKEOFF_ALT": 2.5}


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.asynccontextmanager
async def session() -> AsyncIterator[tuple[MockAutopilot, MavsdkClient]]:
    port = _free_udp_port()
    async with MockAutopilot(local_port=0, remote_ports=[port], params=PARAMS) as ap:
        async with MavsdkClient(f"udpin://127.0.0.1:{port}", connect_timeout_s=10.0) as client:
            yield ap, client


async def _first(gen: Any, pred: Any, timeout_s: float = 15.0) -> Any:
    """The first item of a MAVSDK subscription matching ``pred`` (closes the subscription)."""
    try:
        async with asyncio.timeout(timeout_s):
            async for item in gen:
                if pred(item):
                    return item
    finally:
        await gen.aclose()
    raise AssertionError("subscription ended")


async def _global_position_ok(c: MavsdkClient) -> None:
    """The examples' "Waiting for drone to have a global position estimate"."""
    await _first(c.telemetry.subscribe_health(),
                 lambda h: h.is_global_position_ok and h.is_home_position_ok)


async def _arm_and_take_off(ap: MockAutopilot, c: MavsdkClient) -> None:
    await c.action.arm()
    await c.action.takeoff()
    await ap.wait_until(lambda: ap.mode is FlightMode.HOLD and ap.in_air, 15.0, "take-off")


async def test_do_orbit_example() -> None:
    async with session() as (ap, c):
        await _global_position_ok(c)
        position = await _first(c.telemetry.subscribe_position(), lambda p: True)
        orbit_height = position.absolute_altitude_m + 3.0  # the example: + 10 m
        await _arm_and_take_off(ap, c)
        center_lat, center_lon = 47.398036222362471, 8.5450146439425509  # the example's centre
        await c.action.do_orbit(10.0, 2.0, OrbitYawBehavior.HOLD_FRONT_TO_CIRCLE_CENTER,
                                center_lat, center_lon, orbit_height)
        assert ap.mode is FlightMode.ORBIT
        cn, ce, _ = ap.home.to_ned(center_lat, center_lon, ap.home.alt_m)

        def on_circle() -> bool:
            n, e, d = ap.position_ned_m
            return abs(math.hypot(n - cn, e - ce) - 10.0) < 0.3 and abs(-d - 3.0) < 0.3

        await ap.wait_until(on_circle, 30.0, "on the orbit")
        n, e, _ = ap.position_ned_m
        start = math.atan2(e - ce, n - cn)
        await asyncio.sleep(2.0)
        n, e, _ = ap.position_ned_m
        swept = math.remainder(math.atan2(e - ce, n - cn) - start, 2 * math.pi)
        assert swept * 10.0 == pytest.approx(2.0 * 2.0, abs=1.2)  # clockwise at about 2 m/s
        yaw_to_center = math.atan2(ce - e, cn - n)
        assert abs(math.remainder(ap.vehicle.yaw_rad - yaw_to_center, 2 * math.pi)) < 0.3
        await c.action.return_to_launch()
        assert ap.mode is FlightMode.RTL


async def test_highres_imu_example() -> None:
    async with session() as (ap, c):
        await c.telemetry.set_rate_imu(200.0)
        assert ap.stream_rate_hz("HIGHRES_IMU") == pytest.approx(100.0)  # the physics rate caps it
        imu = await _first(c.telemetry.subscribe_imu(), lambda i: True)
        assert imu.timestamp_us > 0
        assert imu.acceleration_frd.down_m_s2 == pytest.approx(-9.81, abs=0.05)
        assert imu.magnetic_field_frd.down_gauss == pytest.approx(0.43, abs=0.01)
        assert ap.messages_received["COMMAND_LONG"] > 0
        count = 0
        gen = c.telemetry.subscribe_imu()
        loop = asyncio.get_running_loop()
        end = loop.time() + 1.0
        try:
            async for _ in gen:
                count += 1
                if loop.time() > end:
                    break
        finally:
            await gen.aclose()
        assert count > 40


async def test_failure_injection_example() -> None:
    async with session() as (ap, c):
        failure, param = FailureAsync(c._system), ParamAsync(c._system)  # noqa: SLF001 - MAVSDK's System
        await _global_position_ok(c)
        with pytest.raises(FailureError):  # why the example enables it first
            await failure.inject(FailureUnit.SENSOR_GPS, FailureType.OFF, 0)
        await param.set_param_int("SYS_FAILURE_EN", 1)
        assert ap.params.get("SYS_FAILURE_EN") == 1
        await _arm_and_take_off(ap, c)
        position = await _first(c.telemetry.subscribe_position(), lambda p: p.latitude_deg != 0)
        await c.action.goto_location(position.latitude_deg, position.longitude_deg,
                                     position.absolute_altitude_m + 1.0, 0.0)  # the example: + 20 m
        await ap.wait_until(lambda: ap.position_ned_m[2] < -3.3, 10.0, "flown up")
        await failure.inject(FailureUnit.SENSOR_GPS, FailureType.OFF, 0)
        gps = await _first(c.telemetry.subscribe_gps_info(), lambda g: g.fix_type == FixType.NO_FIX, 5.0)
        assert gps.num_satellites == 0
        await param.set_param_int("SYS_FAILURE_EN", 0)
        assert ap.params.get("SYS_FAILURE_EN") == 0


async def test_follow_me_example() -> None:
    async with session() as (ap, c):
        follow_me = FollowMeAsync(c._system)  # noqa: SLF001 - MAVSDK's System
        await _global_position_ok(c)
        await c.action.arm()
        await follow_me.set_config(Config(follow_height_m=8.0, follow_distance_m=2.0, responsiveness=0.02,
                                          follow_angle_deg=180.0))
        assert (ap.params.get("FLW_TGT_HT"), ap.params.get("FLW_TGT_DST")) == (8.0, 2.0)
        await c.action.takeoff()
        await ap.wait_until(lambda: ap.mode is FlightMode.HOLD and ap.in_air, 15.0, "take-off")
        await follow_me.start()
        await _first(c.telemetry.subscribe_flight_mode(), lambda m: m == SdkFlightMode.FOLLOW_ME, 5.0)
        fake_location = [(47.398039859999997, 8.5455725400000002), (47.398036222362471, 8.5450146439425509),
                         (47.397825620791885, 8.5450092830163271)]  # the example's
        for latitude, longitude in fake_location:
            await follow_me.set_target_location(TargetLocation(latitude, longitude, 0.0, 0.0, 0.0, 0.0))
            await asyncio.sleep(2.0)
        tn, te, _ = ap.home.to_ned(*fake_location[-1], ap.home.alt_m)

        def following() -> bool:
            n, e, d = ap.position_ned_m
            return abs(math.hypot(n - tn, e - te) - 2.0) < 0.5 and abs(-d - 8.0) < 0.5

        await ap.wait_until(following, 30.0, "2 m from the last target, 8 m up")
        await follow_me.stop()
        assert ap.mode is FlightMode.HOLD
        await c.action.land()
        assert ap.mode is FlightMode.LAND
