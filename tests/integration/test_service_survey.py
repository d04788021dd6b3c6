"""The take-off survey: after take-off the mission runner turns the vehicle on the spot all
round before the first leg, so the camera has seen beside and behind the start (real mock
autopilot and MAVLink link)."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest

from companion.config import CompanionConfig
from companion.mavlink.vehicle import Vehicle
from companion.service.mission_runner import MissionRunner, position_enu
from companion.sim.autopilot import MockAutopilot
from companion.sim.demo_e2e import free_udp_port
from planner.worker import PlanningService
from semmap.costmap import Costmap

#: A closed-loop flight: the full suite runs it, `make check` does not.
pytestmark = pytest.mark.slow


def _fly(turn_deg: float) -> tuple[list[float], list[np.ndarray]]:
    cfg = CompanionConfig()
    cfg = cfg.model_copy(update={"planner": cfg.planner.model_copy(update={"takeoff_survey_deg": turn_deg})})
    link_port = free_udp_port()
    link = cfg.link.model_copy(update={"url": f"udpin://127.0.0.1:{link_port}"})
    altitude = cfg.planner.flight_altitude_m

    def no_map() -> Costmap:
        raise AssertionError("the survey must not need a map")

    async def main() -> tuple[list[float], list[np.ndarray]]:
        yaws: list[float] = []
        positions: list[np.ndarray] = []
        async with MockAutopilot(local_port=0, remote_ports=(link_port,),
                                 params={"COM_DISARM_PRFLT": -1.0}) as ap, Vehicle(link) as v:
            runner = MissionRunner(v, PlanningService(cfg.planner), no_map, cfg.planner)
            await v.wait_connected(timeout_s=15.0)
            await v.state.wait_for(lambda s: s.home is not None and s.position_ned_m is not None, 15.0,
                                   "home and position")
            done = asyncio.Event()

            async def watch() -> None:
                while not done.is_set():
                    if ap.vehicle.position_ned_m[2] < -(altitude - 0.1):  # airborne at altitude
                        yaws.append(ap.vehicle.yaw_rad)
                        pos = position_enu(v.snapshot())
                        if pos is not None:
                            positions.append(pos[:2].copy())
                    await asyncio.sleep(0.02)

            watcher = asyncio.create_task(watch())
            try:
                await runner.take_off(altitude)
            finally:
                done.set()
                await watcher
            await runner.finish()
        return yaws, positions

    return asyncio.run(main())


def test_take_off_survey_turns_all_round_on_the_spot() -> None:
    yaws, positions = _fly(360.0)
    turned = np.abs(np.diff(np.unwrap(yaws)))
    assert np.degrees(turned.sum()) > 330.0  # the vehicle's own heading went all the way round
    # ... every direction, not back and forth: the heading moved one way only.
    steps = np.diff(np.unwrap(yaws))
    assert np.all(steps >= -math.radians(1.0)) or np.all(steps <= math.radians(1.0))
    assert abs(math.degrees(math.remainder(yaws[-1] - yaws[0], 2 * math.pi))) < 10.0
    xy = np.array(positions)
    assert np.max(np.linalg.norm(xy - xy[0], axis=1)) < 0.15  # on the spot


def test_take_off_survey_off_keeps_heading() -> None:
    yaws, _ = _fly(0.0)
    assert np.degrees(np.abs(np.diff(np.unwrap(yaws))).sum()) < 5.0
