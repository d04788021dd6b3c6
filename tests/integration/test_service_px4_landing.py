"""Waypoints are reached at rest, and the landing is where the mission ended: against a mock
whose velocity loop trails the setpoints like PX4's and whose Land brakes gently and lands
where the vehicle stops (real mock autopilot, MAVLink link and planner process)."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest

from companion.config import CompanionConfig
from companion.mavlink.vehicle import Vehicle
from companion.px4 import FlightMode
from companion.service.mission_runner import SETTLED_SPEED_M_S, Leg, MissionRunner
from companion.service.perception_worker import flight_band
from companion.sim.autopilot import MockAutopilot
from companion.sim.autopilot.behaviour import Px4Behaviour
from companion.sim.demo_e2e import free_udp_port
from planner.worker import PlanningService
from semmap.costmap import Costmap
from semmap.grid import GridSpec

#: A closed-loop flight: the full suite runs it, `make check` does not.
pytestmark = pytest.mark.slow

#: Waypoints (map frame, x east, y north): out across the room and back near the start.
WAYPOINTS_XY_M = ((4.0, 2.5), (0.5, 0.3))


def _speed_xy_m_s(ap: MockAutopilot) -> float:
    vn, ve, _vd = ap.vehicle.velocity_ned_m_s
    return math.hypot(vn, ve)


def test_room_seed_8_lands_on_its_last_waypoint_not_a_metre_on() -> None:
    """PX4 SITL reached the last waypoint of room seed 8 at 0.95 m/s (it trails the setpoints
    by half a second), was handed to Land there, and landed 0.9 m on, in a table. Each
    waypoint now counts as reached only once the vehicle has come to rest on it, and Land is
    engaged on a vehicle at rest."""
    cfg = CompanionConfig()
    cfg = cfg.model_copy(update={"planner": cfg.planner.model_copy(update={"takeoff_survey_deg": 0.0})})
    spec = GridSpec.covering(-2.0, -2.0, 7.0, 5.0, 0.05)
    empty = Costmap(spec, np.zeros(spec.shape_rc, np.uint8), flight_band(cfg), stamp_s=1.0)
    link_port = free_udp_port()
    link = cfg.link.model_copy(update={"url": f"udpin://127.0.0.1:{link_port}"})
    altitude = cfg.planner.flight_altitude_m
    speed_at_reached: list[float] = []
    speed_at_land: list[float] = []

    async def main() -> tuple[float, float]:
        async with MockAutopilot(local_port=0, remote_ports=(link_port,), behaviour=Px4Behaviour(ready_after_s=0.0),
                                 params={"COM_DISARM_PRFLT": -1.0}) as ap, Vehicle(link) as v:
            planning = PlanningService(cfg.planner)
            await asyncio.to_thread(planning.start)
            try:
                runner = MissionRunner(v, planning, lambda: empty, cfg.planner)
                await v.wait_connected(timeout_s=15.0)
                await runner.take_off(altitude)
                for seq, goal in enumerate(WAYPOINTS_XY_M):
                    rep = await runner.fly_leg(Leg(seq, goal, altitude))
                    assert rep.reached, f"leg {seq} not reached"
                    speed_at_reached.append(_speed_xy_m_s(ap))

                async def watch_land() -> None:
                    for _ in range(4000):  # 20 s in 5 ms looks: the speed at the switch
                        if ap.mode is FlightMode.LAND:
                            speed_at_land.append(_speed_xy_m_s(ap))
                            return
                        await asyncio.sleep(0.005)

                watcher = asyncio.create_task(watch_land())
                await runner.finish(FlightMode.LAND)
                await v.state.wait_for(lambda s: not s.armed, 60.0, "the vehicle to land and disarm")
                await watcher
                n, e, _d = ap.vehicle.position_ned_m  # truth: where it stands on the floor
                return e, n
            finally:
                await asyncio.to_thread(planning.close)

    landed_xy = asyncio.run(main())
    # The vehicle's own speed report lags a little: at rest within a few cm/s of the threshold.
    assert max(speed_at_reached) <= SETTLED_SPEED_M_S + 0.05, speed_at_reached
    assert speed_at_land and speed_at_land[0] <= SETTLED_SPEED_M_S + 0.05, speed_at_land
    off_m = math.dist(landed_xy, WAYPOINTS_XY_M[-1])
    assert off_m <= 0.2, f"landed {off_m:.2f} m from the last waypoint, at {landed_xy}"


def test_room_seed_8_stops_on_its_last_waypoint_not_half_a_metre_past_it() -> None:
    """PX4 SITL trails its setpoints, so a path braked at full deceleration was overshot by
    half a metre at its end (room seed 8: into the furniture beyond the last waypoint). The
    last stretch of each path is flown at a crawl; the vehicle stops on the waypoint."""
    cfg = CompanionConfig()
    cfg = cfg.model_copy(update={"planner": cfg.planner.model_copy(update={"takeoff_survey_deg": 0.0})})
    spec = GridSpec.covering(-2.0, -2.0, 7.0, 5.0, 0.05)
    empty = Costmap(spec, np.zeros(spec.shape_rc, np.uint8), flight_band(cfg), stamp_s=1.0)
    link_port = free_udp_port()
    link = cfg.link.model_copy(update={"url": f"udpin://127.0.0.1:{link_port}"})
    altitude = cfg.planner.flight_altitude_m
    overshoot_m: list[float] = []

    async def main() -> None:
        async with MockAutopilot(local_port=0, remote_ports=(link_port,), behaviour=Px4Behaviour(ready_after_s=0.0),
                                 params={"COM_DISARM_PRFLT": -1.0}) as ap, Vehicle(link) as v:
            planning = PlanningService(cfg.planner)
            await asyncio.to_thread(planning.start)
            try:
                runner = MissionRunner(v, planning, lambda: empty, cfg.planner)
                await v.wait_connected(timeout_s=15.0)
                await runner.take_off(altitude)
                for seq, goal in enumerate(WAYPOINTS_XY_M):
                    farthest = [0.0]
                    passed = [False]

                    async def watch(goal: tuple[float, float] = goal, farthest: list[float] = farthest,
                                    passed: list[bool] = passed) -> None:
                        # Truth at 100 Hz: once the vehicle has come within 5 cm of the goal,
                        # how far from it does it get again before the leg ends?
                        while True:
                            n, e, _d = ap.vehicle.position_ned_m
                            d = math.dist((e, n), goal)
                            passed[0] = passed[0] or d <= 0.05
                            if passed[0]:
                                farthest[0] = max(farthest[0], d)
                            await asyncio.sleep(0.01)

                    watcher = asyncio.create_task(watch())
                    try:
                        rep = await runner.fly_leg(Leg(seq, goal, altitude))
                    finally:
                        watcher.cancel()
                    assert rep.reached, f"leg {seq} not reached"
                    overshoot_m.append(farthest[0])
            finally:
                await asyncio.to_thread(planning.close)

    asyncio.run(main())
    # Without the crawl the mock (PX4's velocity loop) overshoots by about 0.3 m.
    assert max(overshoot_m) <= 0.15, f"overshot the waypoints by {overshoot_m} m"
