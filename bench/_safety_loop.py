"""One closed-loop flight in lock-step simulated time, for the safety bench.

The real components, wired as the service wires them, but driven by one simulated clock so
a flight runs faster than real time and the same way on a loaded and an idle machine:

* camera: the room renderer at the vehicle's true pose (``companion.sim.render``);
* perception: the service's :class:`~companion.service.perception_worker.PerceptionPipeline`
  (detector, BoT-SORT tracker, object geometry, semantic map) on the newest frame;
* planning: the service's planner (:class:`planner.planner.Planner`, in process: in lock-step
  nothing else waits for it), its trajectory time-parametrisation, and its path checks
  (as the service's planning process answers them);
* setpoints: the service's SET_POSITION_TARGET_LOCAL_NED encoder, as MAVLink bytes into
* the mock PX4 (:class:`~companion.sim.autopilot.MockAutopilot`): its command handler (arm,
  take-off, offboard), offboard setpoint handling and kinematic vehicle, ticked at 100 Hz.

Compute time is charged to the simulated clock where the real service would wait for it:
a frame's map update becomes visible to the planner ``detect + track + geometry + grid +
costmap`` wall seconds after the frame was taken (the next frame is taken when perception is
free again, at most at ``perception_hz``), and while a plan is computed the vehicle holds at
its last setpoint for the plan's wall time. Rendering and the simulation itself cost nothing.
The leg logic mirrors :class:`companion.service.mission_runner.MissionRunner`: the take-off
survey (a turn on the spot; the leg's time limit starts after it), plan from the setpoint
being flown, follow the trajectory, re-plan when the remaining path crosses a newly mapped
obstacle (checked on every new map, or every ``check_period_s``), back off when too
close, hold and retry when no path exists, snap a blocked goal (and fly on to it once the map frees it).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pymavlink.dialects.v20 import common as mavlink

from bench._safety_scenarios import Scenario
from companion import px4
from companion.config import CompanionConfig
from companion.errors import SimulationError
from companion.geo import GeoOrigin
from companion.mavlink.failsafe import PositionSetpoint
from companion.mavlink.offboard import encode_setpoint
from companion.px4 import FlightMode
from companion.service.mission_runner import (
    DEFAULT_ACCEPTANCE_M,
    RETRY_HOLD_S,
    SETTLED_SPEED_M_S,
    SurveyTurn,
    _remaining,
)
from companion.service.perception_worker import PerceptionPipeline, flight_band, new_semantic_map
from companion.sim.autopilot import MockAutopilot
from companion.sim.autopilot import telemetry as ap_telemetry
from companion.sim.autopilot.behaviour import Px4Behaviour
from companion.sim.render import RoomRenderer
from companion.sim.sim_world import SimPlacement
from planner.planner import Planner
from planner.trajectory import Trajectory, TrajectoryLimits, time_parametrize
from planner.types import PlanResult, PlanStatus
from semmap.costmap import Costmap
from semmap.detection import Detector
from semmap.frames import enu_to_ned, ned_to_enu, yaw_enu_to_ned, yaw_ned_to_enu

log = logging.getLogger(__name__)

PHYSICS_DT_S = 0.01
SETPOINT_PERIOD_S = 1.0 / 30.0
FEED_PERIOD_S = 0.05
#: The mock's home (any point on Earth: the map frame is its local NED origin).
HOME = GeoOrigin(47.397742, 8.545594, 488.0)
COMPANION_SYSID, COMPANION_COMPID = 1, 191


class LockstepAutopilot(MockAutopilot):
    """The mock PX4 on a simulated clock: never opens its socket; :meth:`advance` ticks the
    physics, :meth:`receive` feeds it MAVLink bytes (parsed as the UDP endpoint would).

    It is the naive autopilot (:meth:`Px4Behaviour.naive`): the lock-step flight is a bare
    companion (arm, take off, offboard in the floor frame) measuring the map and planner, not
    a PX4 client; PX4 conformance is measured against the mock's defaults and PX4 SITL."""

    def __init__(self, start_yaw_ned_rad: float, seed: int) -> None:
        super().__init__(local_port=0, remote_ports=(), home=HOME, seed=seed, start_yaw_rad=start_yaw_ned_rad,
                         params={"COM_DISARM_PRFLT": -1.0}, behaviour=Px4Behaviour.naive(),
                         stream_rates_hz={name: 0.0 for name in ap_telemetry.STREAMS})
        self._sim_t_s = 0.0
        self._parser = mavlink.MAVLink(None)
        self._parser.robust_parsing = True

    def now_s(self) -> float:
        return self._sim_t_s

    def advance(self, dt_s: float) -> None:
        """Advance the simulated clock by ``dt_s`` and tick the physics once."""
        self._sim_t_s += dt_s
        self._tick(dt_s)

    def receive(self, data: bytes) -> None:
        """Handle MAVLink bytes sent to the autopilot."""
        for msg in self._parser.parse_buffer(data) or []:
            self._handle(msg)


class _CompanionLink:
    """What :func:`encode_setpoint` needs of a link: a MAVLink encoder and the boot clock."""

    def __init__(self, clock: Any) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=COMPANION_SYSID, srcComponent=COMPANION_COMPID)
        self._clock = clock

    def time_boot_ms(self) -> int:
        return int(1e3 * self._clock())


@dataclass
class FrameLatency:
    """Wall-clock milliseconds of one processed frame."""

    stages_ms: dict[str, float]
    costmap_ms: float
    #: Frame handed to perception -> a setpoint computed on a map that includes it (None when
    #: a newer frame superseded it before the path was checked).
    e2e_ms: float | None = None
    #: The frame's map made the path invalid: its latency includes a re-plan request
    #: (``planner.replan_time_limit_s``).
    replanned: bool = False
    #: The frame was carried by a plan made while holding (a leg's first plan, or a retry
    #: after no path): its latency includes a full planner request (``time_limit_s``).
    from_hold: bool = False


@dataclass
class FlightLog:
    """What one flight recorded (map frame unless noted)."""

    map_mode: str
    detector: str
    t_s: list[float] = field(default_factory=list)
    xyz_map_m: list[tuple[float, float, float]] = field(default_factory=list)
    leg_start_s: float = math.nan
    reached: bool = False
    plans: int = 0
    failed_plans: int = 0
    replans_invalid: int = 0
    plan_ms: list[float] = field(default_factory=list)
    #: The requests among ``plan_ms`` that were re-plans in flight (re-plan budget).
    replan_ms: list[float] = field(default_factory=list)
    #: Map preparation + time to the planner's first valid path (the rest of a request
    #: refines it within the time budget).
    plan_first_ms: list[float] = field(default_factory=list)
    check_ms: list[float] = field(default_factory=list)
    frames: list[FrameLatency] = field(default_factory=list)
    objects_mapped: list[tuple[str, NDArray[np.float64]]] = field(default_factory=list)
    planned_paths_map: list[NDArray[np.float64]] = field(default_factory=list)
    wall_s: float = 0.0
    error: str | None = None

    @property
    def sim_s(self) -> float:
        return self.t_s[-1] if self.t_s else 0.0


def flight_config(cfg: CompanionConfig, scenario: Scenario, placement: SimPlacement, map_mode: str,
                  metric_slice_m: float) -> CompanionConfig:
    """``cfg`` for one flight: altitude, the room as geofence (map frame), the map mode (metric:
    the occupancy grid of a thin depth slice at flight altitude)."""
    alt = scenario.altitude_m
    room = placement.room
    x0, y0 = placement.room_to_map_xy((0.0, 0.0))
    x1, y1 = placement.room_to_map_xy((room.width_m, room.depth_m))
    planner = cfg.planner.model_copy(update={"flight_altitude_m": alt, "geofence_xy_m": (x0, y0, x1, y1)})
    map_update: dict[str, Any] = {"mode": map_mode}
    if map_mode == "metric":
        map_update["scan_band_m"] = (alt - metric_slice_m / 2.0, alt + metric_slice_m / 2.0)
    sim = cfg.sim.model_copy(update={"seed": room.seed})
    return cfg.model_copy(update={"planner": planner, "map": cfg.map.model_copy(update=map_update), "sim": sim})


class LockstepFlight:
    """Flies one scenario with one map mode; :meth:`run` returns the :class:`FlightLog`."""

    def __init__(self, cfg: CompanionConfig, scenario: Scenario, map_mode: str, detector: Detector,
                 detector_name: str, renderer: RoomRenderer, *, perception_hz: float = 4.0,
                 check_period_s: float = 0.0, metric_slice_m: float = 0.1, time_limit_s: float = 40.0,
                 compute_s: float | None = None) -> None:
        self.scenario = scenario
        self.placement = SimPlacement(scenario.room, scenario.start_xy_m)
        self.cfg = flight_config(cfg, scenario, self.placement, map_mode, metric_slice_m)
        self.perception_hz = perception_hz
        self.check_period_s = check_period_s
        self.time_limit_s = time_limit_s
        #: Simulated time each frame's perception and each plan take; None: their wall time (the
        #: bench measures how the machine's latency shapes the flight; a test fixes it so the
        #: flight does not depend on how busy the machine is).
        self.compute_s = compute_s
        gx, gy = self.placement.room_to_map_xy(scenario.goal_xy_m)
        self.goal = np.array([gx, gy])
        self.alt = scenario.altitude_m
        # Facing the goal from the start (PX4 yaw: from north, clockwise).
        self.ap = LockstepAutopilot(math.atan2(gx, gy), seed=scenario.room.seed)
        self.link = _CompanionLink(self.ap.now_s)
        self.smap = new_semantic_map(self.cfg)
        self.pipeline = PerceptionPipeline(self.cfg, self.smap, detector)
        self.band = flight_band(self.cfg)
        #: The room's renderer (shared by the flights of one room: building it is the slow part).
        self.renderer = renderer
        self.T_body_camera = self.cfg.camera.extrinsics.T_body_camera()
        self.T_room_map = np.linalg.inv(self.placement.T_map_room)
        self.planner = Planner(self.cfg.planner)
        self.limits = TrajectoryLimits.from_config(self.cfg.planner)
        self.log = FlightLog(map_mode, detector_name)
        # Perception state: the released costmap and the one in flight.
        self.costmap: Costmap | None = None
        self.map_version = 0
        self._pending: tuple[float, Costmap, FrameLatency] | None = None
        self._unchecked: FrameLatency | None = None
        self._next_capture_s = 0.0
        self._frame_index = 0
        self._setpoint: PositionSetpoint | None = None
        self._next_send_s = 0.0
        #: Latency (ms) of the newest unchecked frame up to the plan it triggers.
        self._e2e_base_ms: float | None = None

    # --- the simulated world ------------------------------------------------------------

    def _step(self) -> None:
        """One physics tick: perception, setpoint stream, autopilot, recording."""
        ap = self.ap
        now = ap.now_s()
        if self._pending is not None and now >= self._pending[0]:
            _, self.costmap, lat = self._pending
            self._pending = None
            self.map_version += 1
            self._unchecked = lat
        if self._pending is None and now >= self._next_capture_s:
            self._perceive(now)
        if self._setpoint is not None and now >= self._next_send_s:
            self._next_send_s = now + SETPOINT_PERIOD_S
            self._send(encode_setpoint(self.link, self._setpoint, 1, 1))  # type: ignore[arg-type]
        ap.advance(PHYSICS_DT_S)
        n, e, d = ap.vehicle.position_ned_m
        self.log.t_s.append(ap.now_s())
        self.log.xyz_map_m.append((e, n, -d))

    def _send(self, msg: Any) -> None:
        self.ap.receive(msg.pack(self.link.mav))

    def _command(self, command: int, *params: float) -> int:
        p = [*params, *([0.0] * (7 - len(params)))]
        self._send(self.link.mav.command_long_encode(1, 1, command, 0, *p))
        return int(self.ap.commands.history[-1].result)  # type: ignore[arg-type]

    def _perceive(self, now: float) -> None:
        """Take a frame at the true pose, run perception on it and schedule its map update."""
        T_map_camera = np.asarray(self.ap.vehicle.T_map_body(), dtype=np.float64) @ self.T_body_camera
        frame = self.renderer.render(self.T_room_map @ T_map_camera, stamp_s=now, index=self._frame_index)
        frame = replace(frame, T_map_camera=T_map_camera)
        self._frame_index += 1
        t0 = time.perf_counter()
        try:
            stages = self.pipeline.process(frame)
        except Exception as exc:  # noqa: BLE001 - the service skips a failing frame too
            log.warning("frame %d skipped: %s", frame.index, exc)
            self._next_capture_s = now + 1.0 / self.perception_hz
            return
        t1 = time.perf_counter()
        costmap = self.pipeline.costmap(self.band)
        t2 = time.perf_counter()
        lat = FrameLatency(stages, 1e3 * (t2 - t1))
        self.log.frames.append(lat)
        busy = t2 - t0 if self.compute_s is None else self.compute_s
        self._pending = (now + busy, costmap, lat)
        self._next_capture_s = now + max(busy, 1.0 / self.perception_hz)

    def _wait(self, duration_s: float) -> None:
        end = self.ap.now_s() + duration_s
        while self.ap.now_s() < end - 1e-9:
            self._step()

    def _pos(self) -> NDArray[np.float64]:
        n, e, d = self.ap.vehicle.position_ned_m
        return np.array(ned_to_enu(n, e, d))

    def _hold(self, xy: NDArray[np.floating]) -> None:
        self._setpoint = PositionSetpoint(enu_to_ned(float(xy[0]), float(xy[1]), self.alt),
                                          yaw_rad=self.ap.vehicle.yaw_rad)

    # --- the flight -----------------------------------------------------------------------

    def run(self) -> FlightLog:
        """Take off, engage offboard, fly the leg; the log holds the whole trajectory."""
        t_wall = time.perf_counter()
        try:
            self._take_off()
            self._fly_leg()
        except SimulationError as exc:
            self.log.error = str(exc)
            log.warning("room %d (%s): %s", self.scenario.room.seed, self.log.map_mode, exc)
        self.log.wall_s = time.perf_counter() - t_wall
        for fp in self.smap.objects:
            self.log.objects_mapped.append((fp.class_name, np.asarray(fp.polygon_xy_m, dtype=np.float64)))
        return self.log

    def _take_off(self) -> None:
        ok = mavlink.MAV_RESULT_ACCEPTED
        if self._command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0) != ok:
            raise SimulationError("arming denied")
        if self._command(mavlink.MAV_CMD_NAV_TAKEOFF, *([math.nan] * 6), HOME.alt_m + self.alt) != ok:
            raise SimulationError("take-off denied")
        deadline = self.ap.now_s() + 30.0
        while self._pos()[2] < self.alt - 0.1:
            if self.ap.now_s() > deadline:
                raise SimulationError(f"did not climb to {self.alt:.2f} m")
            self._step()
        # Offboard as the service engages it: stream the hold setpoint first, then switch.
        self._hold(self._pos()[:2])
        self._wait(self.cfg.link.offboard_warmup_s)
        if self._command(mavlink.MAV_CMD_DO_SET_MODE, *px4.set_mode_params(FlightMode.OFFBOARD)) != ok:
            raise SimulationError("offboard refused")
        self._survey()
        self.log.leg_start_s = self.ap.now_s()

    def _survey(self) -> None:
        """The mission runner's take-off survey (:class:`SurveyTurn`): turn on the spot by
        ``planner.takeoff_survey_deg``, holding position."""
        cfg = self.cfg.planner
        total = math.radians(cfg.takeoff_survey_deg)
        if total <= 0.0:
            return
        xy = self._pos()[:2]
        target = enu_to_ned(float(xy[0]), float(xy[1]), self.alt)
        turn = SurveyTurn(self.ap.vehicle.yaw_rad, total, math.radians(cfg.max_yaw_rate_deg_s))
        deadline = self.ap.now_s() + turn.max_duration_s
        while self.ap.now_s() < deadline:
            yaw = turn.next_yaw(self.ap.vehicle.yaw_rad)
            if yaw is None:
                break
            self._setpoint = PositionSetpoint(target, yaw_rad=yaw)
            for _ in range(int(round(FEED_PERIOD_S / PHYSICS_DT_S))):
                self._step()
        self._setpoint = PositionSetpoint(target, yaw_rad=turn.final_yaw_rad)

    def _plan(self, start: NDArray[np.float64], snap: bool, replan: bool = False) -> PlanResult:
        """Plan on the released costmap; the vehicle holds its setpoint for the plan's wall time.
        ``replan``: the path ahead became blocked; the planner's re-plan budget applies (as in
        the service's mission runner)."""
        if self.costmap is None:
            # Nothing mapped yet: wait for the first frame as the service waits for a costmap.
            while self.costmap is None:
                self._step()
        assert self.costmap is not None
        t0 = time.perf_counter()
        self._adopt_map()
        t1 = time.perf_counter()
        cfg = self.planner.config
        # As the service's planning worker: the budget covers the map preparation too.
        limit = cfg.replan_time_limit_s if replan else cfg.time_limit_s
        result = self.planner.plan(start, self.goal, max(0.0, limit - (t1 - t0)), snap or None)
        wall = time.perf_counter() - t0
        self.log.plans += 1
        self.log.plan_ms.append(1e3 * wall)
        if replan:
            self.log.replan_ms.append(1e3 * wall)
        if math.isfinite(result.first_solution_time_s):
            self.log.plan_first_ms.append(1e3 * (t1 - t0 + result.first_solution_time_s))
        if self._unchecked is not None and self._e2e_base_ms is not None:
            self._unchecked.e2e_ms = self._e2e_base_ms + 1e3 * wall
            self._unchecked.replanned = replan
            self._unchecked.from_hold = not replan
            self._unchecked = None
        self._e2e_base_ms = None
        self._wait(wall if self.compute_s is None else self.compute_s)
        return result

    def _adopt_map(self) -> None:
        """Give the planner the released costmap, as the service sends it to its planning
        process before a plan or a path check (once per map version)."""
        assert self.costmap is not None
        if self.planner.map_version != self.map_version:
            self.planner.set_map(self.costmap, self.map_version)

    def _fly_leg(self) -> None:
        lg = self.log
        end = lg.leg_start_s + self.time_limit_s
        acceptance = DEFAULT_ACCEPTANCE_M
        goal_blocked = False
        replanning = False
        while self.ap.now_s() < end:
            pos = self._pos()
            if np.linalg.norm(pos[:2] - self.goal) <= acceptance:
                lg.reached = True
                return
            start = self._plan_start(pos)
            self._note_frame_for_plan()
            result = self._plan(start, goal_blocked, replanning)
            replanning = False
            goal_blocked = result.status is PlanStatus.GOAL_BLOCKED or result.snapped_goal
            if result.status is PlanStatus.START_BLOCKED and self.costmap is not None:
                self._adopt_map()
                esc = self.planner.escape_point(start)
                if esc is not None and np.linalg.norm(esc - start) < 1.0:
                    traj = time_parametrize(np.vstack([start, esc]), self.alt, self.limits,
                                            initial_yaw_rad=yaw_ned_to_enu(self.ap.vehicle.yaw_rad))
                    self._follow(traj, esc, 0.1, end, check=False)
                    continue
            if not result.ok:
                lg.failed_plans += 1
                if lg.failed_plans >= 20:
                    return
                self._hold(pos[:2])
                self._wait(RETRY_HOLD_S)
                continue
            lg.planned_paths_map.append(result.path_xy_m.copy())
            traj = time_parametrize(result.path_xy_m, self.alt, self.limits,
                                    initial_yaw_rad=yaw_ned_to_enu(self.ap.vehicle.yaw_rad))
            target = self.goal
            if result.snapped_goal and result.goal_xy_m is not None:
                target = np.array(result.goal_xy_m)
                # At rest at the nearest free point to the blocked goal, as the service's runner.
                speed = float(np.hypot(*self.ap.vehicle.state().velocity_ned_m_s[:2]))
                if np.linalg.norm(target - self._pos()[:2]) <= acceptance and speed <= SETTLED_SPEED_M_S:
                    lg.reached = True
                    return
            outcome = self._follow(traj, target, acceptance, end, check=True)
            if outcome == "reached" and target is self.goal:
                lg.reached = True
                return
            if outcome == "invalid":
                lg.replans_invalid += 1
                replanning = True

    def _note_frame_for_plan(self) -> None:
        # A plan on a map no check has looked at yet carries that frame to a setpoint.
        lat = self._unchecked
        if lat is not None and self._e2e_base_ms is None:
            self._e2e_base_ms = sum(lat.stages_ms.values()) + lat.costmap_ms

    def _plan_start(self, pos: NDArray[np.float64]) -> NDArray[np.float64]:
        sp = self._setpoint
        if sp is not None:
            x, y, _z = ned_to_enu(*sp.position_ned_m)
            xy = np.array([x, y])
            if np.linalg.norm(xy - pos[:2]) < 0.5:
                return xy
        return np.asarray(pos[:2], dtype=np.float64)

    def _follow(self, traj: Trajectory, goal: NDArray[np.float64], acceptance_m: float, end_s: float,
                check: bool) -> str:
        """Feed the trajectory; "reached", "invalid" (re-plan), "late" or "timeout"."""
        t_traj = 0.0
        next_check = self.ap.now_s() + self.check_period_s
        settle_s = 5.0
        while self.ap.now_s() < end_s:
            s = traj.sample(t_traj)
            n, e, d = enu_to_ned(*(float(v) for v in s.position_m))
            vn, ve, vd = enu_to_ned(*(float(v) for v in s.velocity_m_s))
            self._setpoint = PositionSetpoint((n, e, d), yaw_rad=yaw_enu_to_ned(s.yaw_rad),
                                              velocity_ned_m_s=(vn, ve, vd))
            pos = self._pos()
            if t_traj >= traj.duration_s:
                if np.linalg.norm(pos[:2] - goal) <= acceptance_m:
                    return "reached"
                if t_traj >= traj.duration_s + settle_s:
                    return "late"
            fresh = self._unchecked is not None
            due = fresh if self.check_period_s <= 0.0 else self.ap.now_s() >= next_check
            if check and due and t_traj < traj.duration_s and self.costmap is not None:
                next_check = self.ap.now_s() + self.check_period_s
                t0 = time.perf_counter()
                self._adopt_map()
                free = self.planner.path_still_valid(_remaining(traj, t_traj))
                check_ms = 1e3 * (time.perf_counter() - t0)
                self.log.check_ms.append(check_ms)
                lat = self._unchecked
                if lat is not None:
                    base = sum(lat.stages_ms.values()) + lat.costmap_ms + check_ms
                    if free:
                        lat.e2e_ms = base
                        self._unchecked = None
                    else:
                        self._e2e_base_ms = base  # completed by the re-plan
                if not free:
                    return "invalid"
            for _ in range(int(round(FEED_PERIOD_S / PHYSICS_DT_S))):
                self._step()
            t_traj += FEED_PERIOD_S
        return "timeout"

    def trajectory_room(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """((N, 3) room-frame positions, (N,) times) from the start of the leg."""
        t = np.asarray(self.log.t_s)
        xyz = np.asarray(self.log.xyz_map_m, dtype=np.float64).reshape(-1, 3)
        k = t >= self.log.leg_start_s if math.isfinite(self.log.leg_start_s) else np.zeros(len(t), bool)
        return self.placement.map_to_room(xyz[k]), t[k]
