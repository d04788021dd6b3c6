"""The companion against real PX4 SITL: what PX4 itself does with our link, missions and service.

One SITL serves the session, so the tests run in this order and each leaves the vehicle on the
ground: readiness and arming; the example square mission; OBSTACLE_DISTANCE; offboard loss
(``companion run`` killed in the air); landing in OFFBOARD and the service taking off again,
whose flight also shows where the service engages OFFBOARD and what PX4 receives from it.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.config import CompanionConfig, LinkConfig
from companion.mavlink.obstacle_distance import ObstacleDistanceFeed, ObstacleDistanceInput
from companion.mavlink.vehicle import Vehicle
from companion.px4 import FlightMode
from companion.sim.px4_probes import (
    engage_check,
    probe_landing_rearm,
    probe_mission_start,
    probe_offboard_loss,
)
from companion.sim.px4_sitl import Px4Sitl
from semmap.costmap import LETHAL_OBSTACLE, Costmap, VerticalBand
from semmap.grid import GridSpec

pytestmark = [pytest.mark.px4, pytest.mark.slow]

#: The service's flight after the re-arm is cut after this long: enough to take off, engage
#: and fly a leg with the obstacle feed, short enough for the session's budget.
REARM_FLIGHT_S = 60.0


def _service_cfg() -> CompanionConfig:
    cfg = CompanionConfig()
    return cfg.model_copy(update={"detector": cfg.detector.model_copy(update={"kind": "oracle"})})


def test_ready_for_takeoff_and_arms(sitl: Px4Sitl) -> None:
    assert sitl.running and "Ready for takeoff!" in sitl.log_text()

    async def arm_disarm() -> tuple[bool, bool]:
        async with Vehicle(LinkConfig(url=sitl.onboard_url)) as v:
            s = await v.wait_connected(15.0)
            await v.state.wait_for(lambda s: s.home is not None and s.position_ned_m is not None, 15.0, "home")
            await v.commands.arm()
            armed = (await v.state.wait_for(lambda s: s.armed, 5.0, "armed")).armed
            await v.commands.disarm()
            disarmed = not (await v.state.wait_for(lambda s: not s.armed, 5.0, "disarmed")).armed
            return armed and s.flight_mode is not None, disarmed

    assert asyncio.run(arm_disarm()) == (True, True)


def test_square_mission_flies_at_home_and_lands(sitl: Px4Sitl) -> None:
    result = asyncio.run(probe_mission_start(sitl))
    assert result.passed, f"{result.detail}\n" + "\n".join(result.px4_log)
    assert not any("far away" in line for line in result.px4_log)


def test_obstacle_distance_reaches_px4(sitl: Px4Sitl) -> None:
    spec = GridSpec(0.05, (-4.0, -4.0), (160, 160))
    cost = np.zeros(spec.shape_rc, dtype=np.uint8)
    X, _ = spec.cell_centers_xy()
    cost[(X > 1.5) & (X < 1.7)] = LETHAL_OBSTACLE  # a wall 1.5 m east
    inp = ObstacleDistanceInput(Costmap(spec, cost, VerticalBand(0.0, 2.0)), (0.0, 0.0), 0.0)

    async def feed() -> dict[str, float]:
        async with Vehicle(LinkConfig(url=sitl.onboard_url)) as v:
            await v.wait_connected(15.0)
            async with ObstacleDistanceFeed(v.link, lambda: inp, rate_hz=10.0):
                await asyncio.sleep(2.0)
                return await asyncio.to_thread(sitl.uorb_top_hz, ["obstacle_distance"])

    rates = asyncio.run(feed())
    assert rates["obstacle_distance"] >= 8.0, rates
    text = sitl.listener("obstacle_distance")
    assert "frame: 12" in text and "increment: 5" in text, text  # body FRD, 5 deg sectors


def test_offboard_loss_hands_over_to_px4_failsafe(sitl: Px4Sitl, tmp_path: Path) -> None:
    result = asyncio.run(probe_offboard_loss(sitl, _service_cfg(), tmp_path))
    assert result.passed, f"{result.detail} {result.figures}\n" + "\n".join(result.px4_log)
    assert result.figures["failsafe_mode"] == FlightMode.LAND.name  # COM_OBL_RC_ACT 4, as the README says


@pytest.fixture(scope="module")
def rearm(sitl: Px4Sitl, tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, Any]:
    """Land in OFFBOARD, then the service's flight (cut after ``REARM_FLIGHT_S``)."""
    return asyncio.run(probe_landing_rearm(sitl, _service_cfg(), tmp_path_factory.mktemp("rearm"),
                                           timeout_s=REARM_FLIGHT_S))


def test_service_takes_off_again_after_landing_in_offboard(rearm: tuple[Any, Any]) -> None:
    result, _ = rearm
    assert result.figures.get("mode_after_landing") == FlightMode.OFFBOARD.name, result.detail
    assert result.passed, f"{result.detail}\n" + "\n".join(result.px4_log)


def test_service_engages_offboard_only_airborne_at_takeoff_height(rearm: tuple[Any, Any]) -> None:
    _, flight = rearm
    assert flight is not None, rearm[0].detail
    ok, detail = engage_check(flight.timeline.events, _service_cfg().planner.flight_altitude_m,
                              path=flight.timeline.path, requests_s=flight.offboard_requests_s)
    assert ok, detail


def test_service_streams_setpoints_and_obstacle_distance_to_px4(rearm: tuple[Any, Any]) -> None:
    _, flight = rearm
    assert flight is not None, rearm[0].detail
    assert flight.uorb_hz.get("offboard_control_mode"), "PX4's uorb never sampled in OFFBOARD"
    assert max(flight.uorb_hz["offboard_control_mode"]) > 0.0
    assert max(flight.uorb_hz.get("obstacle_distance", [0.0])) > 0.0, flight.uorb_hz
