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
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from pymavlink.dialects.v20 import common as mavlink

from companion.errors import MissionError
from companion.mavlink.commands import CommandDeniedError, CommandTemporarilyRejectedError
from companion.mavlink.failsafe import OffboardState, PositionSetpoint
from companion.mavlink.mission_download import MissionItem, waypoint_ned_m
from companion.mavlink.state import HomePosition, MapFrame, VehicleState
from companion.mavlink.vehicle import Vehicle
from companion.px4 import FlightMode
from planner.config import PlannerConfig
from planner.cspace import CSpace, CSpaceParams, build_cspace, update_cspace
from planner.trajectory import Trajectory, TrajectoryLimits, time_parametrize
from planner.types import PlanResult, PlanStatus
from planner.worker import PlanningService
from semmap.costmap import Costmap
from semmap.errors import CompanionError
from semmap.frames import enu_to_ned, ned_to_enu, yaw_enu_to_ned, yaw_ned_to_enu

log = logging.getLogger(__name__)

#: Default distance at which a waypoint counts as reached (metres).
DEFAULT_ACCEPTANCE_M = 0.3
#: How often the setpoint slot is refreshed from the trajectory.
FEED_PERIOD_S = 0.05
#: How often the remaining path is checked against the newest costmap.
CHECK_PERIOD_S = 0.5
#: Hold this long after a failed plan before trying again.
RETRY_HOLD_S = 1.0
#: The take-off survey's yaw setpoint leads the measured heading by this much (degrees) ...
SURVEY_CARROT_DEG = 30.0
#: ... and the survey ends this close to its full turn (degrees) or after twice its time at
#: the planner's yaw rate plus this margin (seconds).
SURVEY_DONE_DEG = 5.0
SURVEY_SETTLE_S = 2.0
#: A re-plan in flight starts this far ahead on the current trajectory (seconds of flight),
#: about 1.5 planning times, so the plan is back before the vehicle gets there.
MIN_REPLAN_LOOKAHEAD_S = 0.6
MAX_REPLAN_LOOKAHEAD_S = 2.0
#: OFFBOARD is engaged only this high above the floor, at least (and at least half the
#: take-off altitude): PX4's take-off aims at its home, whose height can be off by tens of
#: centimetres, so the last part of the climb to the flight altitude is flown in OFFBOARD.
MIN_ENGAGE_HEIGHT_M = 0.3
#: The climb from the engage height to the flight altitude (m/s), and when it is done (m).
CLIMB_SPEED_M_S = 0.5
CLIMB_DONE_M = 0.1
#: OFFBOARD is engaged only with the first setpoint this close to the vehicle (metres).
ENGAGE_MAX_OFFSET_M = 0.5
#: Pause between refused arming attempts (PX4 re-runs its checks at about 1 Hz).
ARM_RETRY_S = 2.0
#: A leg is given up after this many holds for a vehicle that did not follow its setpoints.
MAX_TRACKING_FAULTS = 3
#: A waypoint is reached only by a vehicle this slow (m/s, horizontal): PX4 trails its
#: setpoints by about half a second, so it can be within the acceptance radius still moving
#: at cruise speed, and a leg planned from rest (or PX4's Land) would carry it on.
SETTLED_SPEED_M_S = 0.2
#: Before it is handed to Land or Hold the vehicle comes to rest this close to its last
#: setpoint (m), in at most this long (s): the planner checked that point, not where an
#: overshoot leaves the vehicle.
SETTLED_OFFSET_M = 0.1
SETTLE_TIMEOUT_S = 6.0


@dataclass(frozen=True)
class Leg:
    """One mission leg: fly to ``goal_xy_m`` (map frame ENU) at ``altitude_m``."""

    seq: int
    goal_xy_m: tuple[float, float]
    altitude_m: float
    acceptance_m: float = DEFAULT_ACCEPTANCE_M


def mission_legs(items: Sequence[MissionItem], home: HomePosition, altitude_m: float) -> list[Leg]:
    """The waypoint items of a downloaded mission as legs at ``altitude_m`` (the planner's
    flight altitude: the semantic map's band is built for it). Takeoff, land and RTL items
    are flown by the service itself; other items are skipped with a log line."""
    legs = []
    for it in items:
        if it.command != mavlink.MAV_CMD_NAV_WAYPOINT:
            if it.command not in (mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_CMD_NAV_LAND,
                                  mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH):
                log.info("mission item %d (%s) is not flown by the companion", it.seq, it.command_name)
            continue
        n, e, d = waypoint_ned_m(it, home)
        x, y, _z = ned_to_enu(n, e, d)
        acc = it.param2 if it.param2 > 0 else DEFAULT_ACCEPTANCE_M
        legs.append(Leg(it.seq, (x, y), altitude_m, acc))
    if not legs:
        raise MissionError("the autopilot's mission has no waypoint to fly")
    return legs


def position_enu(state: VehicleState) -> NDArray[np.float64] | None:
    """(3,) the vehicle's map-frame position (z above home), or None before the position
    and the home position are known."""
    pos = state.position_map_m
    return None if pos is None else np.array(pos)


def map_frame_of(state: VehicleState) -> MapFrame:
    """The map frame of ``state``; a :class:`MissionError` before PX4 reports home (no
    setpoint height can be known then)."""
    frame = state.map_frame
    if frame is None:
        raise MissionError("no home position from the autopilot: heights above home are unknown")
    return frame


def horizontal_speed_m_s(state: VehicleState) -> float | None:
    """The vehicle's horizontal speed (m/s), or None before PX4 reports a velocity."""
    vel = state.velocity_ned_m_s
    return None if vel is None else math.hypot(vel[0], vel[1])


def arrived(state: VehicleState, goal_xy_m: NDArray[np.floating], acceptance_m: float) -> bool:
    """The vehicle is within ``acceptance_m`` of ``goal_xy_m`` (map frame) and has come to
    rest there (:data:`SETTLED_SPEED_M_S`)."""
    pos = position_enu(state)
    speed = horizontal_speed_m_s(state)
    return (pos is not None and speed is not None and speed <= SETTLED_SPEED_M_S
            and float(np.linalg.norm(pos[:2] - goal_xy_m)) <= acceptance_m)


def min_engage_height_m(altitude_m: float) -> float:
    """How high above the floor the vehicle must be before OFFBOARD is engaged."""
    return max(MIN_ENGAGE_HEIGHT_M, 0.5 * altitude_m)


def took_off(state: VehicleState, altitude_m: float) -> bool:
    """PX4's take-off to ``altitude_m`` has finished: in the air, out of TAKEOFF (PX4 ends
    it in Hold, and drops an OFFBOARD request made before), and clear of the floor by
    :func:`min_engage_height_m`, by the estimate and by a downward range sensor where there
    is one."""
    height = state.clearance_below_m()
    return (state.in_air and state.flight_mode is not FlightMode.TAKEOFF and height is not None
            and height >= min_engage_height_m(altitude_m))


class SurveyTurn:
    """The take-off survey's yaw setpoints: a turn on the spot by ``total_rad``, one way.

    Fed the measured heading (NED, radians) each step, :meth:`next_yaw` gives the yaw setpoint:
    a carrot :data:`SURVEY_CARROT_DEG` ahead of the heading, never past the end of the turn,
    so the vehicle turns at whatever rate its autopilot allows (PX4's yaw-rate limit may be
    below the planner's) and a setpoint racing more than half a turn ahead can never send it
    back the short way; None once the turn is within :data:`SURVEY_DONE_DEG` of complete.
    Shared by :meth:`MissionRunner.survey` and the lock-step safety bench.
    """

    def __init__(self, yaw0_rad: float, total_rad: float, yaw_rate_rad_s: float) -> None:
        self.yaw0_rad = yaw0_rad
        self.total_rad = total_rad
        self.turned_rad = 0.0
        self._prev = yaw0_rad
        #: Seconds the turn may take: twice its time at ``yaw_rate_rad_s`` plus a margin.
        self.max_duration_s = 2.0 * total_rad / yaw_rate_rad_s + SURVEY_SETTLE_S

    def next_yaw(self, heading_rad: float | None) -> float | None:
        if heading_rad is not None:
            self.turned_rad += math.remainder(heading_rad - self._prev, 2.0 * math.pi)
            self._prev = heading_rad
        left = self.total_rad - self.turned_rad
        if left <= math.radians(SURVEY_DONE_DEG):
            return None
        return math.remainder(self._prev + min(left, math.radians(SURVEY_CARROT_DEG)), 2.0 * math.pi)

    @property
    def final_yaw_rad(self) -> float:
        """The heading the turn ends at (the setpoint to hold afterwards)."""
        return math.remainder(self.yaw0_rad + self.total_rad, 2.0 * math.pi)


class PathChecker:
    """The planner's own configuration space on the newest costmap (updated by window), so
    the service judges paths exactly as the planner does: ``path_free`` for the remaining
    path, ``escape_point`` when the vehicle has ended up too close to an obstacle."""

    def __init__(self, cfg: PlannerConfig) -> None:
        self.params = CSpaceParams(vehicle_radius_m=cfg.vehicle_radius_m, unknown_cost=cfg.unknown_cost,
                                   clearance_decay_m=cfg.clearance_decay_m, geofence_xy_m=cfg.geofence_xy_m)
        self.cs: CSpace | None = None
        self._version = 0

    def update(self, costmap: Costmap) -> CSpace:
        """Adopt ``costmap`` (full build on a new grid or band, else the changed window)."""
        self._version += 1
        if self.cs is None or self.cs.spec != costmap.spec or self.cs.band != costmap.band:
            self.cs = build_cspace(costmap, self.params, self._version)
        else:
            self.cs, _window = update_cspace(self.cs, costmap, self._version)
        return self.cs

    def path_free(self, path_xy_m: NDArray[np.floating]) -> bool:
        """True if the (K, 2) polyline is free on the last costmap."""
        return self.cs is None or self.cs.path_free(path_xy_m)

    def escape_point(self, xy_m: NDArray[np.floating], extra_m: float = 0.05) -> NDArray[np.float64] | None:
        """The nearest point to ``xy_m`` where the vehicle fits with ``extra_m`` to spare."""
        cs = self.cs
        if cs is None:
            return None
        rows, cols = np.nonzero(cs.free & (cs.clearance_m >= cs.free_threshold_m + extra_m))
        if len(rows) == 0:
            return None
        spec = cs.spec
        cx = spec.origin_xy_m[0] + (cols + 0.5) * spec.resolution_m
        cy = spec.origin_xy_m[1] + (rows + 0.5) * spec.resolution_m
        k = int(np.argmin((cx - xy_m[0]) ** 2 + (cy - xy_m[1]) ** 2))
        return np.array([cx[k], cy[k]])


@dataclass
class LegReport:
    """How one leg went."""

    seq: int
    goal_xy_m: tuple[float, float]
    reached: bool = False
    plans: int = 0
    replans_invalid: int = 0
    failed_plans: int = 0
    plan_ms: list[float] = field(default_factory=list)
    duration_s: float = 0.0
    final_error_m: float = math.nan
    snapped_goal: bool = False  # the waypoint was blocked; the nearest free point was flown to
    tracking_faults: int = 0  # holds because the vehicle did not follow its setpoints


class MissionRunner:
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
        self.checker = PathChecker(planner_cfg)
        #: Latest plan duration (ms), for the per-stage timings.
        self.last_plan_ms: float | None = None
        self.capture_time = capture_time
        #: Per plan: capture of the newest frame in the planned-on costmap -> the plan's first
        #: setpoint handed to the setpoint stream (ms).
        self.frame_to_setpoint_ms: deque[float] = deque(maxlen=2000)
        self.reports: list[LegReport] = []

    # --- vehicle steps ------------------------------------------------------------------

    async def take_off(self, altitude_m: float, timeout_s: float = 30.0) -> None:
        """Arm once PX4 is ready, take off to ``altitude_m`` above PX4's home (set where it
        armed), wait until the take-off has finished, engage OFFBOARD holding where the vehicle
        is, and climb (or descend) on the spot to ``altitude_m`` above the floor."""
        v = self.vehicle
        if not v.snapshot().in_air:
            await self.arm_when_ready()
            # PX4 takes the altitude above home as AMSL; home streams only on change, so the
            # copy we hold can predate the one PX4 set at arming: climb from where it stands.
            state = v.snapshot()
            ground_above_home_m = 0.0
            if state.global_position is not None and state.home is not None:
                ground_above_home_m = state.global_position.altitude_amsl_m - state.home.altitude_amsl_m
            commanded_s = time.monotonic()
            await v.commands.takeoff(altitude_m + ground_above_home_m)
            # PX4 reports its mode in a 1 Hz heartbeat: until one sent after the command, the
            # mode shown is the one before the take-off, not its end.
            await v.state.wait_for(lambda s: took_off(s, altitude_m) and s.heartbeat_age_s is not None
                                   and time.monotonic() - s.heartbeat_age_s > commanded_s, timeout_s,
                                   f"the take-off to {altitude_m:.2f} m to finish")
        await self.engage_here(altitude_m)
        await self.climb_to(altitude_m)
        await self.survey(altitude_m)

    async def arm_when_ready(self) -> None:
        """Wait for PX4's readiness (pre-arm checks, home, local position), leave a mode PX4
        will not arm in (it keeps OFFBOARD or LAND after landing), then arm, retrying a
        refusal a bounded number of times."""
        v = self.vehicle
        await v.state.wait_for(lambda s: s.ready_to_arm, v.cfg.ready_timeout_s,
                               "the autopilot to be ready to arm (pre-arm checks, home, local position)")
        await self.make_armable()
        for attempt in range(v.cfg.arm_retries + 1):
            try:
                await v.commands.arm()
                break
            except (CommandDeniedError, CommandTemporarilyRejectedError) as exc:
                if attempt == v.cfg.arm_retries:
                    raise MissionError(f"arming refused {attempt + 1} times: {exc}") from exc
                log.warning("arming refused (%s); retrying in %.0f s", exc, ARM_RETRY_S)
                await asyncio.sleep(ARM_RETRY_S)
                await self.make_armable()
        await v.state.wait_for(lambda s: s.armed, v.cfg.heartbeat_timeout_s, "the vehicle to report armed")

    async def make_armable(self) -> None:
        """Put a vehicle on the ground into Hold, the one mode it is armed in here: PX4 keeps
        OFFBOARD or Land after a landing, refuses Position and Altitude without RC, and
        armed in Mission flies its own uploaded mission."""
        v = self.vehicle
        state = v.snapshot()
        if state.in_air or state.armed or state.flight_mode is FlightMode.HOLD:
            return
        assert state.flight_mode is not None
        log.info("vehicle on the ground in %s: switching to HOLD so it can arm", state.flight_mode.name)
        await v.commands.set_mode(FlightMode.HOLD)
        await v.state.wait_for(lambda s: s.flight_mode is FlightMode.HOLD, v.cfg.heartbeat_timeout_s,
                               "the vehicle to report HOLD")

    async def survey(self, altitude_m: float, turn_deg: float | None = None) -> None:
        """Turn on the spot by ``turn_deg`` (default ``planner.takeoff_survey_deg``), holding
        position at ``altitude_m``, so the map has seen all round (:class:`SurveyTurn`)."""
        total = math.radians(self.cfg.takeoff_survey_deg if turn_deg is None else turn_deg)
        snap = self.vehicle.snapshot()
        xy = self._hold_xy()
        if total <= 0.0 or xy is None:
            return
        if snap.yaw_ned_rad is None:
            log.warning("survey skipped: no heading from the autopilot yet")
            return
        turn = SurveyTurn(snap.yaw_ned_rad, total, math.radians(self.cfg.max_yaw_rate_deg_s))
        target = map_frame_of(snap).to_ned(float(xy[0]), float(xy[1]), altitude_m)
        deadline = time.monotonic() + turn.max_duration_s
        log.info("survey: turning %.0f deg on the spot", math.degrees(total))
        while time.monotonic() < deadline:
            self._check_offboard()
            yaw = turn.next_yaw(self.vehicle.snapshot().yaw_ned_rad)
            if yaw is None:
                break
            self.vehicle.offboard.set_setpoint(PositionSetpoint(target, yaw_rad=yaw))
            await asyncio.sleep(FEED_PERIOD_S)
        else:
            log.warning("survey: turned %.0f of %.0f deg before its time ran out",
                        math.degrees(turn.turned_rad), math.degrees(total))
        self.vehicle.offboard.set_setpoint(PositionSetpoint(target, yaw_rad=turn.final_yaw_rad))

    async def engage_here(self, altitude_m: float) -> None:
        """Hold where the vehicle is and engage OFFBOARD; only in the air, clear of the floor
        (:func:`took_off`), with that hold near the vehicle, so OFFBOARD never starts on the
        ground or with a setpoint somewhere else."""
        state = self.vehicle.snapshot()
        pos = position_enu(state)
        if pos is None:
            raise MissionError("no vehicle position (or no floor height) to engage offboard from")
        if not state.in_air or not took_off(state, altitude_m):
            raise MissionError(f"not engaging offboard: the vehicle is not airborne clear of the floor "
                               f"({'in the air' if state.in_air else 'on the ground'}, "
                               f"{pos[2]:.2f} m above the floor, range below "
                               f"{'none' if state.range_down_m is None else f'{state.range_down_m:.2f} m'}, "
                               f"{min_engage_height_m(altitude_m):.2f} m needed)")
        xy = pos[:2].copy()
        self.hold_at(xy, float(pos[2]))
        sp = self.vehicle.offboard.status().setpoint
        assert sp is not None
        offset = math.dist(sp.position_ned_m, map_frame_of(state).to_ned(*pos))
        if offset > ENGAGE_MAX_OFFSET_M:
            raise MissionError(f"not engaging offboard: the first setpoint is {offset:.2f} m from the vehicle")

        async def follow_climb() -> None:
            # PX4's Hold may still be climbing while the stream warms up (1 s, then up to a
            # heartbeat for the switch): the hold rises with the vehicle, never pulling it back
            # down towards the floor when OFFBOARD takes over.
            top_m = float(pos[2])
            while True:
                now = position_enu(self.vehicle.snapshot())
                if now is not None and float(now[2]) > top_m:
                    top_m = float(now[2])
                    self.hold_at(xy, top_m)
                await asyncio.sleep(FEED_PERIOD_S)

        follower = asyncio.create_task(follow_climb())
        try:
            await self.vehicle.offboard.engage()
        finally:
            follower.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await follower

    async def climb_to(self, altitude_m: float, timeout_s: float = 20.0) -> None:
        """Climb (or descend) on the spot, in OFFBOARD, to ``altitude_m`` above the floor, the
        setpoint moving at :data:`CLIMB_SPEED_M_S` so the vehicle never lags it far."""
        pos = position_enu(self.vehicle.snapshot())
        xy = self._hold_xy()
        if pos is None or xy is None:
            raise MissionError("no vehicle position to climb from")
        z0 = float(pos[2])
        t0 = time.monotonic()
        while True:
            self._check_offboard()
            step = CLIMB_SPEED_M_S * (time.monotonic() - t0)
            # The last setpoint is the altitude itself (z0 plus the rest need not equal it exactly).
            ramp_done = step >= abs(altitude_m - z0)
            z_sp = altitude_m if ramp_done else z0 + math.copysign(step, altitude_m - z0)
            self.hold_at(xy, z_sp)
            now = position_enu(self.vehicle.snapshot())
            if ramp_done and now is not None and abs(float(now[2]) - altitude_m) <= CLIMB_DONE_M:
                return
            if time.monotonic() - t0 > timeout_s:
                raise MissionError(f"the climb to {altitude_m:.2f} m did not end within {timeout_s:.0f} s")
            await asyncio.sleep(FEED_PERIOD_S)

    def _hold_xy(self) -> NDArray[np.float64] | None:
        """Where the climb and the survey hold (map frame xy): the setpoint being streamed
        (OFFBOARD was engaged on it, at the vehicle), so a vehicle still drifting from PX4's
        take-off is brought back rather than followed; the vehicle's position before any."""
        state = self.vehicle.snapshot()
        sp = self.vehicle.offboard.status().setpoint
        frame = state.map_frame
        if sp is not None and frame is not None and self.vehicle.offboard.state.streams:
            x, y, _z = frame.from_ned(*sp.position_ned_m)
            return np.array([x, y])
        pos = position_enu(state)
        return None if pos is None else np.asarray(pos[:2], dtype=np.float64)

    def hold_at(self, xy_m: NDArray[np.floating], altitude_m: float) -> None:
        """Replace the setpoint with a hold at ``xy_m`` (map frame) and ``altitude_m``, keeping yaw."""
        snap = self.vehicle.snapshot()
        self.vehicle.offboard.set_setpoint(PositionSetpoint(
            map_frame_of(snap).to_ned(float(xy_m[0]), float(xy_m[1]), altitude_m), yaw_rad=snap.yaw_ned_rad))

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
                rep.reached = True
                break
            start = self._plan_start(pos)
            # A waypoint that turned out to lie in (or too near) a mapped object is replaced
            # by the nearest point the vehicle fits (the planner's goal snapping).
            result, costmap = await self._plan(start, leg.goal_xy_m, snap_goal=goal_blocked, replan=replanning)
            replanning = False
            goal_blocked = result.status is PlanStatus.GOAL_BLOCKED
            rep.plans += 1
            rep.plan_ms.append(1e3 * result.planning_time_s)
            if result.status is PlanStatus.START_BLOCKED:
                await asyncio.to_thread(self.checker.update, costmap)
                esc = self.checker.escape_point(start)
                if esc is not None and np.linalg.norm(esc - start) < 1.0:
                    log.info("leg %d: too close to an obstacle; backing off %.2f m first", leg.seq,
                             float(np.linalg.norm(esc - start)))
                    await self._follow(time_parametrize(np.vstack([start, esc]), leg.altitude_m, self.limits,
                                                        initial_yaw_rad=self._yaw_enu()),
                                       Leg(leg.seq, (float(esc[0]), float(esc[1])), leg.altitude_m, 0.1),
                                       check=False)
                    continue
            if not result.ok:
                rep.failed_plans += 1
                log.warning("leg %d: no path (%s: %s); holding", leg.seq, result.status.value, result.reason)
                if rep.failed_plans >= self.max_failed_plans:
                    break
                self.hold_at(pos[:2], leg.altitude_m)
                await asyncio.sleep(RETRY_HOLD_S)
                continue
            if self.on_path is not None:
                self.on_path(result.path_xy_m)
            traj = time_parametrize(result.path_xy_m, leg.altitude_m, self.limits,
                                    initial_yaw_rad=self._yaw_enu())
            target = leg
            if result.snapped_goal and result.goal_xy_m is not None:
                log.warning("leg %d: waypoint blocked on the map; flying to the nearest free point (%.2f, %.2f) m",
                            leg.seq, *result.goal_xy_m)
                target = Leg(leg.seq, result.goal_xy_m, leg.altitude_m, leg.acceptance_m)
                goal = np.array(result.goal_xy_m)
                rep.snapped_goal = True
            capture_s = self.capture_time(costmap) if self.capture_time is not None else None
            outcome = await self._follow(traj, target, capture_mono_s=capture_s, rep=rep)
            if outcome == "reached":
                rep.reached = True
                break
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

    def _check_offboard(self) -> None:
        st = self.vehicle.offboard.state
        if st in (OffboardState.YIELDED, OffboardState.IDLE):
            raise MissionError(f"offboard control ended ({st.value}: {self.vehicle.offboard.failsafe.reason})")

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
        goal = np.array(leg.goal_xy_m)
        t_traj = 0.0
        t_cap = math.inf  # while a re-plan is pending, trajectory time stops at its start point
        last = time.monotonic()
        next_check = last + CHECK_PERIOD_S
        settle_s = 5.0
        ctl = self.vehicle.offboard
        checking: asyncio.Task[tuple[bool, float | None]] | None = None
        replan: asyncio.Task[tuple[PlanResult, Costmap]] | None = None
        try:
            while True:
                now = time.monotonic()
                st = ctl.state
                if st is OffboardState.ACTIVE:
                    t_traj = min(t_traj + now - last, t_cap)
                elif st is OffboardState.HOLDING and ctl.failsafe.tracking_fault:
                    return "tracking"
                elif st is OffboardState.LINK_LOST and self.vehicle.connected:
                    await self._reengage(leg)
                    return "invalid"  # PX4's failsafe moved the vehicle: re-plan from where it is
                else:
                    self._check_offboard()
                last = now
                s = traj.sample(t_traj)
                n, e, d = map_frame_of(self.vehicle.snapshot()).to_ned(*(float(v) for v in s.position_m))
                vn, ve, vd = enu_to_ned(*(float(v) for v in s.velocity_m_s))
                ctl.set_setpoint(PositionSetpoint((n, e, d), yaw_rad=yaw_enu_to_ned(s.yaw_rad),
                                                  velocity_ned_m_s=(vn, ve, vd)))
                if capture_mono_s is not None:
                    self.frame_to_setpoint_ms.append(1e3 * (time.monotonic() - capture_mono_s))
                    capture_mono_s = None
                snap = self.vehicle.snapshot()
                pos = position_enu(snap)
                if replan is None and t_traj >= traj.duration_s and pos is not None:
                    if arrived(snap, goal, leg.acceptance_m):
                        return "reached"
                    if t_traj >= traj.duration_s + settle_s:
                        return "late"
                if replan is not None and replan.done():
                    result, costmap = replan.result()
                    replan = None
                    if rep is not None:
                        rep.plans += 1
                        rep.plan_ms.append(1e3 * result.planning_time_s)
                    if not result.ok or result.snapped_goal:
                        log.info("leg %d: re-plan on the fly gave %s; stopping to re-plan from here",
                                 leg.seq, result.status.value if not result.ok else "a moved goal")
                        return "invalid"
                    path = np.vstack([_between(traj, t_traj, t_cap), result.path_xy_m])
                    speed = float(np.linalg.norm(s.velocity_m_s[:2]))
                    traj = time_parametrize(path, leg.altitude_m, self.limits, initial_yaw_rad=s.yaw_rad,
                                            initial_speed_m_s=speed)
                    t_traj, t_cap = 0.0, math.inf
                    next_check = now + CHECK_PERIOD_S
                    capture_mono_s = self.capture_time(costmap) if self.capture_time is not None else None
                    if self.on_path is not None:
                        self.on_path(path)
                    continue
                if check and replan is None:
                    if checking is None and now >= next_check and pos is not None and t_traj < traj.duration_s:
                        checking = asyncio.create_task(self._check_ahead(traj, t_traj))
                    elif checking is not None and checking.done():
                        free, t_start = checking.result()
                        checking = None
                        next_check = now + CHECK_PERIOD_S
                        if not free:
                            if rep is not None:
                                rep.replans_invalid += 1
                            if t_start is None or t_start <= t_traj:
                                log.info("leg %d: the path just ahead crosses a newly mapped obstacle; "
                                         "stopping to re-plan", leg.seq)
                                return "invalid"
                            start = traj.sample(t_start).position_m[:2]
                            log.info("leg %d: the path ahead crosses a newly mapped obstacle; re-planning "
                                     "from (%.2f, %.2f) m, %.1f s ahead, while flying on", leg.seq,
                                     start[0], start[1], t_start - t_traj)
                            t_cap = t_start
                            replan = asyncio.create_task(self._plan(np.asarray(start, dtype=np.float64),
                                                                    leg.goal_xy_m, replan=True))
                await asyncio.sleep(FEED_PERIOD_S)
        finally:
            for task in (checking, replan):
                if task is not None and not task.done():
                    task.cancel()

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

    async def _check_ahead(self, traj: Trajectory, t_s: float) -> tuple[bool, float | None]:
        """Is the rest of ``traj`` from ``t_s`` free on the newest costmap? If not, also the
        trajectory time from which to re-plan without stopping: the stretch up to it must be
        free (None when even a short one is not)."""
        if await self._path_free(_remaining(traj, t_s)):
            return True, None
        plan_s = self.last_plan_ms / 1e3 if self.last_plan_ms is not None else 0.5
        lookahead = min(MAX_REPLAN_LOOKAHEAD_S, max(MIN_REPLAN_LOOKAHEAD_S, 1.5 * plan_s + 0.3))
        for ahead in (lookahead, 0.5 * lookahead):
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


def _remaining(traj: Trajectory, t_s: float) -> NDArray[np.float64]:
    """(K, 2) the rest of the trajectory's path from a little ahead of time ``t_s`` (the
    vehicle's own neighbourhood is not judged: it is where the vehicle already is)."""
    t_ahead = min(traj.duration_s, t_s + 0.3)
    ahead = traj.sample(t_ahead).position_m[:2]
    seg = max(0, int(np.searchsorted(traj.seg_t0_s, t_ahead, side="right")) - 1)
    return np.vstack([ahead[None, :], traj.waypoints_xy_m[seg + 1:]])


def _between(traj: Trajectory, t0_s: float, t1_s: float) -> NDArray[np.float64]:
    """(K, 2) the trajectory's path from time ``t0_s`` to ``t1_s`` (its corners in between)."""
    t1_s = min(t1_s, traj.duration_s)
    a = traj.sample(t0_s).position_m[:2]
    b = traj.sample(t1_s).position_m[:2]
    s0 = max(0, int(np.searchsorted(traj.seg_t0_s, t0_s, side="right")) - 1)
    s1 = max(0, int(np.searchsorted(traj.seg_t0_s, t1_s, side="right")) - 1)
    return np.vstack([a[None, :], traj.waypoints_xy_m[s0 + 1:s1 + 1], b[None, :]])
