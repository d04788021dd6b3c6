"""Fly a mission leg by leg in OFFBOARD with the semantic planner between waypoints.

The mission uploaded to the autopilot (by MAVSDK or a ground station) is downloaded through our
link and turned into :class:`Leg` s (map-frame goals). After take-off the vehicle turns once on
the spot (:meth:`MissionRunner.survey`) so the map has seen all round it. Each leg is planned
by the planning worker process on the semantic map's costmap at the flight band, time-parametrised, and flown
by feeding the offboard controller's setpoint slot. While flying, the remaining path is
re-checked against every new costmap; when it has become invalid (an object appeared on it)
the leg is re-planned without stopping: from a point a little ahead on the current
trajectory, which the vehicle keeps flying towards until the new path is spliced in at its
current speed (it stops and re-plans from where it is only when the obstacle is just ahead).
A failed plan holds position and retries.
So every leg avoids hollow-bottom furniture the mission author never knew about.

The steps live beside it: legs and arrival in :mod:`~companion.service.mission_legs`, the
take-off and engage sequence in :mod:`~companion.service.takeoff`, one trajectory's flight in
:mod:`~companion.service.leg_follow`.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from companion.errors import MissionError
from companion.mavlink.vehicle import Vehicle
from companion.px4 import FlightMode
from companion.service.leg_follow import (
    CHECK_PERIOD_S,
    LegFollow,
    _between,
    _remaining,
)
from companion.service.mission_legs import (
    DEFAULT_ACCEPTANCE_M,
    FEED_PERIOD_S,
    SETTLED_SPEED_M_S,
    Leg,
    LegReport,
    arrived,
    horizontal_speed_m_s,
    map_frame_of,
    mission_legs,
    position_enu,
)
from companion.service.takeoff import (
    SURVEY_CARROT_DEG,
    SurveyTurn,
    TakeoffSteps,
    min_engage_height_m,
    took_off,
)
from planner.config import PlannerConfig
from planner.trajectory import Trajectory, TrajectoryLimits, time_parametrize
from planner.types import PlanResult, PlanStatus
from planner.worker import PlanningService
from semmap.costmap import Costmap
from semmap.errors import CompanionError
from semmap.frames import yaw_ned_to_enu

#: The names the service, the benches and the tests import from here (defined in the step
#: modules :mod:`~companion.service.mission_legs`, :mod:`~companion.service.takeoff` and
#: :mod:`~companion.service.leg_follow`).
__all__ = [
    "CHECK_PERIOD_S", "DEFAULT_ACCEPTANCE_M", "FEED_PERIOD_S", "SETTLED_SPEED_M_S", "SURVEY_CARROT_DEG",
    "Leg", "LegReport", "MissionRunner", "SurveyTurn", "arrived", "horizontal_speed_m_s",
    "map_frame_of", "min_engage_height_m", "mission_legs", "position_enu", "took_off", "_between", "_remaining",
]

log = logging.getLogger(__name__)

#: Hold this long after a failed plan before trying again.
RETRY_HOLD_S = 1.0
#: A re-plan in flight starts this far ahead on the current trajectory (seconds of flight),
#: about 1.5 planning times, so the plan is back before the vehicle gets there.
MIN_REPLAN_LOOKAHEAD_S = 0.6
MAX_REPLAN_LOOKAHEAD_S = 2.0
#: A leg is given up after this many holds for a vehicle that did not follow its setpoints.
MAX_TRACKING_FAULTS = 3
#: Before it is handed to Land or Hold the vehicle comes to rest this close to its last
#: setpoint (m), in at most this long (s): the planner checked that point, not where an
#: overshoot leaves the vehicle.
SETTLED_OFFSET_M = 0.1
SETTLE_TIMEOUT_S = 6.0


class MissionRunner(TakeoffSteps):
    """Flies legs with ``vehicle`` (already connected) using ``planning`` on the costmaps
    from ``costmap_source`` (callable returning the current costmap at the flight band;
    called in a worker thread). ``on_path`` is told each new planned path (MQTT, logs).
    ``capture_time``: the capture time (``time.monotonic()`` s) of the newest camera frame in
    a costmap, when known; each plan's frame-to-setpoint latency is then recorded in
    :attr:`frame_to_setpoint_ms`."""

    def __init__(self, vehicle: Vehicle, planning: PlanningService, costmap_source: Callable[[], Costmap],
                 planner_cfg: PlannerConfig, *, on_path: Callable[[NDArray[np.float64]], None] | None = None,
                 max_failed_plans: int = 20, leg_timeout_s: float = 120.0,
                 capture_time: Callable[[Costmap], float | None] | None = None) -> None:
        self.vehicle = vehicle
        self.planning = planning
        self.costmap_source = costmap_source
        self.cfg = planner_cfg
        self.limits = TrajectoryLimits.from_config(planner_cfg)
        self.on_path = on_path
        self.max_failed_plans = max_failed_plans
        self.leg_timeout_s = leg_timeout_s
        self._map_version = 0
        self._versioned: Costmap | None = None
        #: Latest plan duration (ms), for the per-stage timings.
        self.last_plan_ms: float | None = None
        self.capture_time = capture_time
        #: Per plan: capture of the newest frame in the planned-on costmap -> the plan's first
        #: setpoint handed to the setpoint stream (ms).
        self.frame_to_setpoint_ms: deque[float] = deque(maxlen=2000)
        self.reports: list[LegReport] = []


    # --- planning -----------------------------------------------------------------------

    async def _plan(self, start_xy: NDArray[np.float64], goal_xy: tuple[float, float],
                    snap_goal: bool = False, replan: bool = False) -> tuple[PlanResult, Costmap]:
        """Plan on the newest costmap; ``replan``: in flight, with the planner's
        ``replan_time_limit_s`` budget instead of ``time_limit_s``."""
        costmap = await asyncio.to_thread(self.costmap_source)
        limit = self.planning.config.replan_time_limit_s if replan else None
        result = await asyncio.to_thread(self.planning.plan, costmap, self._version_of(costmap), start_xy, goal_xy,
                                         limit, snap_goal or None)
        self.last_plan_ms = 1e3 * result.planning_time_s
        return result, costmap

    def _version_of(self, costmap: Costmap) -> int:
        """The map version of ``costmap`` for the planning worker: a new one for each new
        costmap object (the worker then applies only the changed window)."""
        if costmap is not self._versioned:
            self._versioned = costmap
            self._map_version += 1
        return self._map_version

    async def _path_free(self, path_xy_m: NDArray[np.float64]) -> bool:
        """Whether the (K, 2) path is free on the newest costmap, judged in the planning
        process (a configuration-space update costs tens of ms of numpy/scipy that must not
        compete with the setpoint stream for this process's GIL)."""
        costmap = await asyncio.to_thread(self.costmap_source)
        free = await asyncio.to_thread(self.planning.path_free, costmap, self._version_of(costmap), path_xy_m)
        return True if free is None else free  # no answer: keep flying; the next check asks again

    # --- legs ---------------------------------------------------------------------------

    async def fly(self, legs: Sequence[Leg]) -> list[LegReport]:
        """Fly every leg in order; returns one report per leg (``reached`` False when a leg
        was given up). Raises :class:`MissionError` when the vehicle left OFFBOARD."""
        for leg in legs:
            self.reports.append(await self.fly_leg(leg))
        return self.reports

    async def fly_leg(self, leg: Leg) -> LegReport:
        """Plan and fly to one goal, re-planning when the path becomes invalid."""
        rep = LegReport(leg.seq, leg.goal_xy_m)
        t_leg = time.monotonic()
        goal = np.array(leg.goal_xy_m)
        goal_blocked = False
        replanning = False  # a plan after the path ahead became blocked (re-plan budget)
        log.info("leg %d: to (%.2f, %.2f) m", leg.seq, *leg.goal_xy_m)
        while time.monotonic() - t_leg < self.leg_timeout_s:
            self._check_offboard()
            snap = self.vehicle.snapshot()
            pos = position_enu(snap)
            if pos is None:
                await asyncio.sleep(RETRY_HOLD_S)
                continue
            if arrived(snap, goal, leg.acceptance_m):
                rep.reached, rep.snapped_goal = True, False
                break
            start = self._plan_start(pos)
            # A waypoint that turned out to lie in (or too near) a mapped object is replaced
            # by the nearest point the vehicle fits (the planner's goal snapping).
            result, costmap = await self._plan(start, leg.goal_xy_m, snap_goal=goal_blocked, replan=replanning)
            replanning = False
            # Once blocked, every plan asks for the nearest free point again: the planner
            # returns the waypoint itself as soon as the map frees it.
            goal_blocked = result.status is PlanStatus.GOAL_BLOCKED or result.snapped_goal
            rep.plans += 1
            rep.plan_ms.append(1e3 * result.planning_time_s)
            if result.status is PlanStatus.START_BLOCKED and await self._back_off(leg, start, costmap):
                continue
            if not result.ok:
                if await self._hold_after_failed_plan(leg, rep, result, pos):
                    continue
                break
            if self.on_path is not None:
                self.on_path(result.path_xy_m)
            traj = time_parametrize(result.path_xy_m, leg.altitude_m, self.limits,
                                    initial_yaw_rad=self._yaw_enu())
            target = leg
            if result.snapped_goal and result.goal_xy_m is not None:
                stand_in = np.asarray(result.goal_xy_m, dtype=np.float64)
                # At rest there, like any waypoint: a leg that ended as the vehicle passed
                # through the stand-in's acceptance circle would leave it braking up to the
                # circle's radius beyond, away from the waypoint.
                if arrived(self.vehicle.snapshot(), stand_in, leg.acceptance_m):
                    rep.reached = rep.snapped_goal = True
                    goal = stand_in
                    break
                target = self._snapped_target(leg, result.goal_xy_m, rep)
            capture_s = self.capture_time(costmap) if self.capture_time is not None else None
            outcome = await self._follow(traj, target, capture_mono_s=capture_s, rep=rep)
            if outcome == "reached" and target is leg:
                rep.reached, rep.snapped_goal = True, False
                break
            if outcome == "reached":
                # At the stand-in for a blocked waypoint, chosen on an older map: the next plan
                # flies on to the waypoint if the map has freed it since, or ends the leg here.
                continue
            if outcome == "tracking":
                rep.tracking_faults += 1
                if rep.tracking_faults >= MAX_TRACKING_FAULTS:
                    raise MissionError(f"leg {leg.seq}: the vehicle did not follow its setpoints "
                                       f"{rep.tracking_faults} times ({self.vehicle.offboard.failsafe.reason})")
                log.warning("leg %d: the vehicle is not following its setpoints; re-planning from "
                            "where it is", leg.seq)
            replanning = outcome == "invalid"
        rep.duration_s = time.monotonic() - t_leg
        pos = position_enu(self.vehicle.snapshot())
        if pos is not None:
            rep.final_error_m = float(np.linalg.norm(pos[:2] - goal))
        log.info("leg %d: %s after %.1f s (%d plans, %d re-plans on a changed map)", leg.seq,
                 "reached" if rep.reached else "NOT reached", rep.duration_s, rep.plans, rep.replans_invalid)
        return rep

    async def _back_off(self, leg: Leg, start: NDArray[np.float64], costmap: Costmap) -> bool:
        """Fly to the nearest point the vehicle fits when it is less than a metre away; False
        when there is none that near (the leg then holds like any failed plan)."""
        esc = await asyncio.to_thread(self.planning.escape_point, costmap, self._version_of(costmap), start)
        if esc is None or np.linalg.norm(esc - start) >= 1.0:
            return False
        log.info("leg %d: too close to an obstacle; backing off %.2f m first", leg.seq,
                 float(np.linalg.norm(esc - start)))
        await self._follow(time_parametrize(np.vstack([start, esc]), leg.altitude_m, self.limits,
                                            initial_yaw_rad=self._yaw_enu()),
                           Leg(leg.seq, (float(esc[0]), float(esc[1])), leg.altitude_m, 0.1),
                           check=False)
        return True

    async def _hold_after_failed_plan(self, leg: Leg, rep: LegReport, result: PlanResult,
                                      pos: NDArray[np.float64]) -> bool:
        """Count a failed plan and hold where the vehicle is before the next try; False when
        the leg has used up its failed plans (no hold)."""
        rep.failed_plans += 1
        log.warning("leg %d: no path (%s: %s); holding", leg.seq, result.status.value, result.reason)
        if rep.failed_plans >= self.max_failed_plans:
            return False
        self.hold_at(pos[:2], leg.altitude_m)
        await asyncio.sleep(RETRY_HOLD_S)
        return True

    @staticmethod
    def _snapped_target(leg: Leg, goal_xy_m: tuple[float, float], rep: LegReport) -> Leg:
        """The leg to the nearest free point the planner moved a blocked waypoint to."""
        log.warning("leg %d: waypoint blocked on the map; flying to the nearest free point (%.2f, %.2f) m",
                    leg.seq, *goal_xy_m)
        rep.snapped_goal = True
        return Leg(leg.seq, goal_xy_m, leg.altitude_m, leg.acceptance_m)

    def _yaw_enu(self) -> float | None:
        yaw_ned = self.vehicle.snapshot().yaw_ned_rad
        return None if yaw_ned is None else yaw_ned_to_enu(yaw_ned)

    def _plan_start(self, pos_enu: NDArray[np.float64]) -> NDArray[np.float64]:
        """Where a new plan starts: the setpoint being flown when it is near the vehicle (it
        lies on the last checked path, and the vehicle brakes towards it without
        overshooting), else the vehicle's position."""
        sp = self.vehicle.offboard.status().setpoint
        frame = self.vehicle.snapshot().map_frame
        if sp is not None and frame is not None and self.vehicle.offboard.state.streams:
            x, y, _z = frame.from_ned(*sp.position_ned_m)
            xy = np.array([x, y])
            if np.linalg.norm(xy - pos_enu[:2]) < 0.5:
                return xy
        return np.asarray(pos_enu[:2], dtype=np.float64)


    async def _follow(self, traj: Trajectory, leg: Leg, check: bool = True,
                      capture_mono_s: float | None = None, rep: LegReport | None = None) -> str:
        """Feed the trajectory; "reached", "invalid" (re-plan from here), "tracking" (the
        vehicle did not follow and is held where it is: re-plan from there) or "late".
        ``capture_mono_s``: capture time of the newest frame in the map the trajectory was
        planned on (its first setpoint's latency is recorded).

        Trajectory time only advances while the controller flies our setpoints (ACTIVE), so
        after a hold (stale pose or map, link loss) the vehicle resumes where it stopped.

        With ``check``, the rest of the path is checked on the newest costmap every
        ``CHECK_PERIOD_S`` (in the planning process, off this loop). When it has become
        blocked, the leg is re-planned *without stopping*: the new plan starts at a point a
        little ahead on the current trajectory (where the vehicle will be when the plan
        arrives, if that stretch is still free); the vehicle keeps flying towards it, and the
        new path is spliced in at the current speed. Only when that stretch is blocked too,
        or the re-plan fails, does the vehicle stop ("invalid") and re-plan from where it is.
        """
        return await LegFollow(self, traj, leg, check, capture_mono_s, rep).run()

    async def _reengage(self, leg: Leg) -> None:
        """The link is back after a loss: PX4's offboard-loss failsafe has flown the vehicle
        meanwhile (Position mode descends and lands without RC). Engage again only if it is
        still airborne, with a hold where it is at the leg's altitude; a landed vehicle ends
        the mission (PX4 would accept OFFBOARD on the ground, disarmed)."""
        state = self.vehicle.snapshot()
        pos = position_enu(state)
        if not (state.in_air and state.armed) or pos is None:
            raise MissionError(f"leg {leg.seq}: the vehicle landed during the link loss "
                               f"({state.flight_mode.name if state.flight_mode else 'unknown mode'}, "
                               f"{'armed' if state.armed else 'disarmed'}); not re-engaging offboard")
        log.warning("autopilot link back with the vehicle in the air: holding at (%.2f, %.2f) m and "
                    "re-engaging offboard", pos[0], pos[1])
        self.hold_at(pos[:2], leg.altitude_m)
        try:
            await self.vehicle.offboard.engage()
        except CompanionError as exc:
            log.warning("re-engaging offboard failed: %s; retrying", exc)

    async def _check_ahead(self, traj: Trajectory, t_now: Callable[[], float]) -> tuple[bool, float | None]:
        """Is the rest of ``traj`` from the trajectory time ``t_now()`` free on the newest
        costmap? If not, also the trajectory time from which to re-plan without stopping: the
        stretch up to it must be free (None when even a short one is not)."""
        t0 = time.monotonic()
        if await self._path_free(_remaining(traj, t_now())):
            return True, None
        # The re-plan must be back before the vehicle reaches its start: judged by the last
        # plan and by this check's own round trip, which shows how fast the planning process
        # answers now (a loaded CPU can take it from tens of ms to a second).
        plan_s = self.last_plan_ms / 1e3 if self.last_plan_ms is not None else 0.5
        plan_s = max(plan_s, time.monotonic() - t0)
        lookahead = min(MAX_REPLAN_LOOKAHEAD_S, max(MIN_REPLAN_LOOKAHEAD_S, 1.5 * plan_s + 0.3))
        for ahead in (lookahead, 0.5 * lookahead):
            # Ahead of where the vehicle is by now: the first answer can take longer than the
            # lookahead (the planning process prepares the changed map first, on a loaded CPU).
            t_s = t_now()
            t_start = min(traj.duration_s, t_s + ahead)
            if await self._path_free(_between(traj, t_s, t_start)):
                return False, t_start
        return False, None

    async def finish(self, then: FlightMode = FlightMode.LAND) -> None:
        """Bring the vehicle to rest on its last setpoint (:meth:`settle`), then hand it to
        ``then`` (LAND or HOLD) and stop streaming: PX4's Land and Hold brake gently and stop
        (and land) up to a metre on from where they were engaged at cruise speed."""
        if self.vehicle.offboard.state.streams:
            await self.settle()
            await self.vehicle.offboard.release(then)

    async def settle(self, timeout_s: float = SETTLE_TIMEOUT_S) -> None:
        """Keep the current setpoint until the vehicle is within :data:`SETTLED_OFFSET_M` of it
        and slower than :data:`SETTLED_SPEED_M_S` (at most ``timeout_s``, then a warning)."""
        deadline = time.monotonic() + timeout_s
        while True:
            state = self.vehicle.snapshot()
            sp = self.vehicle.offboard.status().setpoint
            frame = state.map_frame
            pos = position_enu(state)
            if sp is None or frame is None or pos is None:
                return
            goal = np.array(frame.from_ned(*sp.position_ned_m)[:2])
            if arrived(state, goal, SETTLED_OFFSET_M):
                return
            if time.monotonic() > deadline or not self.vehicle.offboard.state.streams:
                speed = horizontal_speed_m_s(state)
                log.warning("the vehicle did not come to rest on its last setpoint within %.0f s "
                            "(%.2f m from it, %s m/s)", timeout_s, float(np.linalg.norm(pos[:2] - goal)),
                            "unknown" if speed is None else f"{speed:.2f}")
                return
            await asyncio.sleep(FEED_PERIOD_S)

