"""The service's landing when the SLAM pose (PX4's only position without GPS) is lost, against
the mock autopilot with PX4's defaults: EKF2_NOAID_TOUT 5 s, MPC_LAND_SPEED 0.7 m/s. The
landing must touch down while PX4 still has a position; after that PX4's Land descends
without one and drifts (companion.sim.autopilot.mock: Descend)."""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import AsyncIterator
from pathlib import Path

import numpy as np
import pytest
import yaml
from pymavlink.dialects.v20 import common as mavlink
from raw_mavlink_client import RawClient

from companion.config import load_config
from companion.mavlink.link import MavlinkLink
from companion.mavlink.vision import vision_odometry_message
from companion.px4 import FlightMode
from companion.service.position_source import ServiceLocalization
from companion.sim.autopilot import MockAutopilot
from semmap.errors import ConfigError

pytestmark = [pytest.mark.asyncio, pytest.mark.timeout(90)]

NAN = math.nan
ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
ALTITUDE_M = 1.5


def _cfg(tmp_path: Path, **link: object) -> ServiceLocalization:
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump({
        "service": {"localization": "slam"},
        "link": {"external_vision": True, "vision_is_position_source": True, **link},
        "planner": {"flight_altitude_m": ALTITUDE_M},
    }))
    return ServiceLocalization(load_config(path))


@contextlib.asynccontextmanager
async def flying_on_vision() -> AsyncIterator[tuple[MockAutopilot, RawClient, MavlinkLink, asyncio.Event]]:
    """The GPS-denied mock (PX4's default timeout and land speed) at ALTITUDE_M on the true
    pose as vision, with the service's link; setting the event stops the vision."""
    client = RawClient()
    async with MavlinkLink("udpin://127.0.0.1:0", heartbeat_rate_hz=2.0) as link:
        port = link.transport.local_address[1]  # type: ignore[attr-defined]
        async with MockAutopilot(local_port=0, remote_ports=[client.port, port], params={"MPC_TKO_SPEED": 3.0},
                                 gps_denied=True, vision_gain=0.5) as ap:
            client.ap_addr = ("127.0.0.1", ap.local_port)
            stop_vision = asyncio.Event()

            async def keep_reading() -> None:
                while True:
                    client._drain()
                    await asyncio.sleep(0.01)

            async def vision() -> None:
                while not stop_vision.is_set():
                    stamp, T = ap.T_map_body()
                    client.send(vision_odometry_message(client, T, int(stamp * 1e6),  # type: ignore[arg-type]
                                                        position_std_m=0.05))
                    await asyncio.sleep(1.0 / 30.0)

            tasks = [asyncio.create_task(keep_reading()), asyncio.create_task(vision())]
            try:
                await client.wait_ready(timeout_s=8.0)
                await ap.wait_until(lambda: ap.position_ok, 5.0, "a position from vision")
                assert await client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == ACCEPTED
                assert await client.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, NAN, NAN, NAN,
                                            ap.home.alt_m + ALTITUDE_M) == ACCEPTED
                await ap.wait_until(lambda: ap.mode is FlightMode.HOLD and ap.in_air, 15.0, "take-off")
                yield ap, client, link, stop_vision
            finally:
                for t in tasks:
                    t.cancel()
    client.close()


async def test_the_slam_lost_lands_before_px4_drops_its_position(tmp_path: Path) -> None:
    loc = _cfg(tmp_path)
    async with flying_on_vision() as (ap, client, link, stop_vision):
        landed_at: list[float] = []

        async def land() -> None:
            landed_at.append(time.monotonic())
            assert await client.command(mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, NAN, NAN, NAN, NAN) == ACCEPTED

        guard = loc.loss_guard(link, lambda: ap.in_air, land)
        assert guard is not None
        lost: list[float] = []
        guard.vision_age_s = lambda: time.monotonic() - lost[0] if lost else 0.0  # type: ignore[method-assign]
        task = asyncio.create_task(guard.run())
        try:
            await asyncio.sleep(1.0)  # the guard has read PX4's parameters
            lost_xy = np.array(ap.position_ned_m[:2])
            stop_vision.set()
            lost.append(time.monotonic())
            await ap.wait_until(lambda: not ap.in_air, 20.0, "the landing")
        finally:
            task.cancel()
        detail = f"land commanded {landed_at[0] - lost[0] if landed_at else None} s after the loss, {ap.failsafes}"
        assert [a.value for _, a, _ in guard.events] == ["hold", "land"], detail
        # Down before EKF2_NOAID_TOUT: PX4's own failsafe (Land without a position) never acted,
        # and the vehicle touched down where it was when the pose was lost.
        assert ap.failsafes == [], detail
        assert float(np.linalg.norm(np.array(ap.position_ned_m[:2]) - lost_xy)) < 0.1, detail


async def test_a_landing_time_px4s_estimate_cannot_carry_is_refused(tmp_path: Path) -> None:
    # 4 s, then 1.5 m at 0.7 m/s (2.1 s): PX4's 5 s are over long before the touchdown.
    loc = _cfg(tmp_path, vision_lost_land_s=4.0)
    async with flying_on_vision() as (ap, client, link, _stop):
        async def land() -> None:
            raise AssertionError("no landing expected")

        guard = loc.loss_guard(link, lambda: ap.in_air, land)
        assert guard is not None
        with pytest.raises(ConfigError, match=r"link\.vision_lost_land_s.*EKF2_NOAID_TOUT.*MPC_LAND_SPEED"):
            await asyncio.wait_for(guard.run(), 10.0)
