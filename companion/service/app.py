"""The companion service: camera -> perception -> semantic map -> planner -> setpoints.

:class:`CompanionService` has an explicit lifecycle:

* ``configure()`` builds everything from the config without touching the world: the semantic
  map (restored from the last checkpoint), the perception pipeline and the planning service;
* ``activate()`` (inside :meth:`run`) opens every long-lived part as an async context manager
  under one exit stack, and starts the service's loops: the planner process, the perception process (camera,
  detector, tracker, semantic map and its checkpoints; :mod:`.perception_process`), the
  MAVLink vehicle (setpoint stream, telemetry, OBSTACLE_DISTANCE), the flight log, the MQTT
  bridge and the systemd watchdog. The service process itself only runs the event loop, so
  the setpoint stream never waits for perception's share of the GIL;
* ``deactivate()`` (when ``stop`` is set, e.g. on SIGTERM) holds or lands first
  (``service.on_sigterm``), then stops streaming, and the checkpointer saves the map. Every
  step of the stop is bounded (:mod:`.shutdown`): what does not end in time is logged with its
  stack and the worker processes' state, and left behind, so the service always ends.

With ``fly_mission`` the autopilot's mission is downloaded and flown leg by leg with the
semantic planner (:mod:`companion.service.mission_runner`); goals and mission commands also
come over MQTT (:mod:`companion.service.mission_control`). The status, telemetry, objects and
map go to the ground link from :mod:`companion.service.status`. This module only wires.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import sys
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from companion.background import TASK_STOP_TIMEOUT_S, stop_tasks
from companion.config import CompanionConfig
from companion.ground import MqttBridge
from companion.mavlink.obstacle_distance import ObstacleDistanceInput
from companion.mavlink.vehicle import Vehicle
from companion.px4 import FlightMode
from companion.service.checkpoint import checkpoint_path, restore_map
from companion.service.flight_log import FlightLog
from companion.service.latency import LatencyStats
from companion.service.mission_control import MissionControl
from companion.service.mission_runner import LegReport, MissionRunner
from companion.service.perception_process import STOP_TIMEOUT_S as PERCEPTION_STOP_TIMEOUT_S
from companion.service.perception_process import PerceptionProcess
from companion.service.perception_worker import (
    PerceptionPipeline,
    new_semantic_map,
)
from companion.service.position_source import ServiceLocalization
from companion.service.shutdown import (
    BoundedExit,
    ShutdownWatch,
    Worker,
    bounded,
    dump_state,
    kill_workers,
)
from companion.service.status import StatusPublisher
from companion.service.vision_loss import VisionLossGuard
from companion.sources.base import FrameSource
from companion.sources.poses import SharedPoseHistory, TelemetryPosedSource, TelemetryPoseRecorder
from companion.systemd_notify import SystemdNotifier, Watchdog
from planner.worker import PlanningService
from semmap.costmap import ObjectFootprint
from semmap.errors import CompanionError, MapError
from semmap.semantic_map import SemanticMap

log = logging.getLogger(__name__)

T = TypeVar("T")

#: GIL switch interval while the service runs (Python's default is 5 ms).
SWITCH_INTERVAL_S = 0.001
#: The systemd watchdog stops pinging when no frame went through perception for this long.
PERCEPTION_SILENCE_S = 15.0
#: On stop with ``service.on_sigterm: land``: wait this long for the touchdown before exiting.
LAND_WAIT_S = 30.0
#: The stop's bounds: the hand-over (mission cancelled, hold or land commanded, touchdown),
#: the service's loops and flight task once cancelled, each part's close, the perception
#: process's (its last map save; it kills the child itself past its own bound).
DEACTIVATE_TIMEOUT_S = LAND_WAIT_S + 20.0
PART_CLOSE_TIMEOUT_S = 10.0
PERCEPTION_CLOSE_TIMEOUT_S = PERCEPTION_STOP_TIMEOUT_S + 20.0
#: Past this from the stop's start the watch thread dumps the state, kills the worker
#: processes and (``companion run``) ends the process: the sum of the bounds above and a margin.
SHUTDOWN_TIMEOUT_S = (DEACTIVATE_TIMEOUT_S + TASK_STOP_TIMEOUT_S + 6 * PART_CLOSE_TIMEOUT_S
                      + PERCEPTION_CLOSE_TIMEOUT_S + 15.0)


@contextlib.contextmanager
def frozen_heap() -> Iterator[None]:
    """Collect once, then keep the collector off every object alive now until exit.

    A full collection walks every object the imports and the configuration left, on the
    event-loop thread, which stalls the setpoint stream for longer than its period;
    ``gc.freeze`` moves them to the permanent generation so later collections walk only what
    the flight allocates. It runs once, before anything streams (freezing again after start-up
    would keep start-up garbage from the collector). An outer freeze is left in place on exit."""
    already_frozen = gc.get_freeze_count() > 0
    t0 = time.perf_counter()
    gc.collect()
    gc.freeze()
    log.info("heap frozen for the flight: %d objects, collection took %.0f ms",
             gc.get_freeze_count(), 1e3 * (time.perf_counter() - t0))
    try:
        yield
    finally:
        if not already_frozen:
            gc.unfreeze()


@dataclass
class ServiceReport:
    """What a run did (for summaries and tests)."""

    legs: list[LegReport] = field(default_factory=list)
    mission_error: str | None = None
    frames_processed: int = 0
    frames_dropped: int = 0
    frames_failed: int = 0
    #: Frames skipped because no pose was known at their time (no telemetry yet, or lost).
    frames_unposed: int = 0
    stage_timings: dict[str, dict[str, float]] = field(default_factory=dict)
    plan_ms: list[float] = field(default_factory=list)
    checkpoints: int = 0
    flight_log_rows: int = 0
    #: {"frame_to_map": ..., "frame_to_setpoint": ...}: {"count", "p50_ms", "p95_ms", "max_ms"}
    #: (see :meth:`CompanionService.latency_summary`).
    latency: dict[str, dict[str, float | int]] = field(default_factory=dict)
    #: SLAM counters when ``service.localization`` is ``slam`` (see :class:`ServiceLocalization`).
    localization: dict[str, float | int | str] = field(default_factory=dict)
    #: The steps of the stop that overran their bound (their state was logged), in order.
    stop_overruns: list[str] = field(default_factory=list)


class CompanionService:
    """The whole onboard pipeline for one vehicle.

    ``frame_source``: the camera (a simulated one when the simulated world runs in-process).
    ``object_classes``: object id -> class for the simulator's oracle detector.
    ``fly_mission``: download and fly the autopilot's mission once connected.
    ``land_after_mission``: land at the end of the mission (else hold in OFFBOARD).
    """

    def __init__(self, cfg: CompanionConfig, frame_source: FrameSource, *, out_dir: str | Path | None = None,
                 object_classes: Mapping[int, str] | None = None, fly_mission: bool = False,
                 land_after_mission: bool = True, notifier: SystemdNotifier | None = None) -> None:
        self.cfg = cfg
        self.frame_source = frame_source
        self.out_dir = Path(out_dir if out_dir is not None else cfg.service.output_dir)
        self.object_classes = object_classes
        self.fly_mission = fly_mission
        self.notifier = notifier or SystemdNotifier.from_env()
        self.state = "created"
        self.report = ServiceReport()
        self.smap: SemanticMap | None = None
        #: Only set by callers that run perception in this process (the service runs it in
        #: :attr:`perception`, a separate process).
        self.pipeline: PerceptionPipeline | None = None
        self.vehicle: Vehicle | None = None
        self.perception: PerceptionProcess | None = None
        #: The planner process's client while the service runs.
        self.planning: PlanningService | None = None
        self.localization = ServiceLocalization(cfg)
        #: The autopilot's recent poses from telemetry: a camera that delivers no pose (the
        #: RealSense) gets its frames posed from them (:mod:`companion.sources.poses`).
        self.pose_history = SharedPoseHistory()
        self.runner: MissionRunner | None = None
        self.ground: MqttBridge | None = None
        self.restored = False
        #: The mission, goals and ground commands (the flight task of this run).
        self.missions = MissionControl(cfg, land_after_mission=land_after_mission)
        #: Set when the mission has ended (flown, failed or aborted), not by a pause.
        self.mission_done = self.missions.done
        #: The status, telemetry, objects and map on the ground link while the service runs.
        self.status: StatusPublisher | None = None
        self._background_tasks: set[asyncio.Task[None]] = set()
        self._stop: asyncio.Event | None = None
        self._t0 = time.monotonic()
        #: Called once the service is active (tests inject faults from here).
        self.on_active: Callable[[CompanionService], Any] | None = None
        #: ``companion run`` sets an exit code: a stop the event loop cannot end ends the process.
        self.hung_stop_exit_code: int | None = None
        self._workers = [Worker("perception", lambda: self.perception.worker if self.perception else None),
                         Worker("planner", lambda: self.planning.worker if self.planning else None)]

    # --- lifecycle ----------------------------------------------------------------------

    def configure(self) -> None:
        """Load the map (restored from the checkpoint when there is one). The perception
        process restores the same checkpoint and owns the map while the service runs;
        :attr:`smap` is its final state once :meth:`run` returns."""
        restored = restore_map(self.cfg, checkpoint_path(self.cfg))
        self.restored = restored is not None
        self.smap = restored if restored is not None else new_semantic_map(self.cfg)
        self.state = "configured"
        log.info("service configured (%s map)", "restored" if self.restored else "new")

    async def run(self, stop: asyncio.Event) -> ServiceReport:
        """Activate, run until ``stop`` is set (a caller that flies one mission sets it once
        :attr:`mission_done` is) or one of the service's loops fails, deactivate. Returns the
        run's report; a loop's failure is raised once the service has stopped."""
        if self.state != "configured":
            self.configure()
        assert self.smap is not None
        self._stop = stop
        # Threads left in this process (MAVLink/MQTT helpers, the perception update reader)
        # are light; still hand the GIL over every millisecond rather than every 5.
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        with frozen_heap():
            return await self._run(stop)

    async def _run(self, stop: asyncio.Event) -> ServiceReport:
        cfg = self.cfg
        # Localization (SLAM on the camera's frames, in the perception process) re-poses the
        # frames before perception when enabled; it streams its pose to PX4 from here.
        loc = self.localization
        # A frame that comes without a pose gets the autopilot's at its stamp (telemetry).
        posed = TelemetryPosedSource(self.frame_source, self.pose_history, cfg.camera.extrinsics.T_body_camera())
        perception = self.perception = PerceptionProcess(cfg, loc.source(posed), self.object_classes)
        watch = ShutdownWatch(SHUTDOWN_TIMEOUT_S, self._workers, exit_code=self.hung_stop_exit_code)
        try:
            await self._run_parts(stop, perception, watch)
        finally:
            watch.disarm()
        # The perception process has stopped and saved the map: its final state.
        self._record_perception(perception)
        log.info("service stopped")
        return self.report

    def _bounded(self, cm: contextlib.AbstractAsyncContextManager[T], what: str,
                 timeout_s: float = PART_CLOSE_TIMEOUT_S) -> BoundedExit[T]:
        """A part whose close is bounded; an overrun is logged with the service's state."""
        return BoundedExit(cm, timeout_s, what, on_overrun=self._stop_overran)

    def _stop_overran(self, why: str) -> None:
        self.report.stop_overruns.append(why)
        dump_state(why, self._workers)

    async def _run_parts(self, stop: asyncio.Event, perception: PerceptionProcess, watch: ShutdownWatch) -> None:
        """Open every part under one exit stack, serve until ``stop``, close them (each close
        bounded); ``watch`` is armed before they close, however the run ends."""
        async with contextlib.AsyncExitStack() as stack:
            try:
                await self._open_and_serve(stack, stop, perception, watch)
            finally:
                watch.arm()

    async def _open_and_serve(self, stack: contextlib.AsyncExitStack, stop: asyncio.Event,
                              perception: PerceptionProcess, watch: ShutdownWatch) -> None:
        cfg = self.cfg
        loc = self.localization
        assert self.smap is not None
        planning = self.planning = PlanningService(cfg.planner)
        await asyncio.to_thread(planning.start)
        # Joining the worker waits up to seconds: off the loop (MQTT and the link stay served).
        stack.push_async_callback(self._close_planning, planning)
        await stack.enter_async_context(BoundedExit(perception, PERCEPTION_CLOSE_TIMEOUT_S, "the perception process",
                                                    on_overrun=self._perception_overran))
        # OBSTACLE_DISTANCE from the flight-band costmap lets PX4's collision prevention
        # (CP_DIST) stop the vehicle short of what the map holds, whoever flies it.
        self.vehicle = await stack.enter_async_context(self._bounded(
            Vehicle(cfg.link, is_map_fresh=perception.is_fresh, is_pose_fresh=self._pose_fresh,
                    obstacle_source=self._obstacle_input), "the MAVLink vehicle"))
        recorder = TelemetryPoseRecorder(self.pose_history, cfg.link.target_system, cfg.link.target_component,
                                         remote_to_local=self.vehicle.autopilot_clock.to_local,
                                         map_frame=lambda: self.vehicle.snapshot().map_frame if self.vehicle else None)
        stack.callback(self.vehicle.link.add_listener(recorder.handle, recorder.MESSAGES))
        await stack.enter_async_context(self._bounded(loc.vision_stream(self.vehicle.link), "the vision stream"))
        vehicle = self.vehicle
        missions = self.missions
        guard = loc.loss_guard(vehicle.link, lambda: vehicle.snapshot().in_air,
                               lambda: missions.land_here("the SLAM pose (PX4's position source) is lost"),
                               height_m=lambda: vehicle.snapshot().height_above_floor_m)
        flight_log = await stack.enter_async_context(
            self._bounded(FlightLog(self.out_dir / "flight_log.csv", self.vehicle), "the flight log"))
        self.ground = await stack.enter_async_context(self._bounded(MqttBridge.from_config(cfg), "the MQTT bridge"))
        self.runner = MissionRunner(self.vehicle, planning, perception.costmap, cfg.planner,
                                    on_path=missions.on_path, capture_time=perception.capture_time)
        missions.bind(self.vehicle, self.runner, self.ground)
        status = self.status = StatusPublisher(cfg, self.vehicle, self.ground, perception, self.runner, loc,
                                               self.notifier, state=lambda: self.state, map_spec=self.smap.spec,
                                               started_at=self._t0)
        status.update_goal_fence()
        watchdog = await stack.enter_async_context(self._bounded(Watchdog(self.notifier), "the systemd watchdog"))
        watchdog.register("status-loop", 5.0)
        # A hung perception process (or camera) stops the pings: systemd restarts us.
        watchdog.register("perception", PERCEPTION_SILENCE_S)
        perception.on_frame = lambda: watchdog.alive("perception")
        perception.on_failed = lambda: self._background(missions.land_here("perception is gone", lost=True),
                                                        "perception-lost")
        self.state = "active"
        self.notifier.ready("active")
        log.info("service active")
        try:
            await self._serve_until_stopped(stop, status, watchdog, guard, watch)
        finally:
            self.state = "stopped"
            self.report.flight_log_rows = flight_log.rows
            self.report.mission_error = missions.error
            if self.runner is not None:
                self.report.legs = list(self.runner.reports)
                self.report.plan_ms = [ms for r in self.runner.reports for ms in r.plan_ms]

    def _perception_overran(self, why: str) -> None:
        self._stop_overran(why)
        kill_workers(self._workers[:1])  # its last map save is lost; the checkpoint before it stays

    async def _close_planning(self, planning: PlanningService) -> None:
        """Stop the planner process (off the loop); past its bound, kill it."""
        ended, _ = await bounded(asyncio.to_thread(planning.close), PART_CLOSE_TIMEOUT_S, "closing the planner process")
        if not ended:
            self._stop_overran(f"closing the planner process overran {PART_CLOSE_TIMEOUT_S:.0f} s")
            kill_workers(self._workers[1:])

    async def _serve_until_stopped(self, stop: asyncio.Event, status: StatusPublisher, watchdog: Watchdog,
                                   guard: VisionLossGuard | None, watch: ShutdownWatch) -> None:
        """Run the status and ground-command loops (the vision-loss guard, the mission and the
        ``on_active`` hook when there are) until ``stop`` or until one of them fails; then
        arm ``watch``, deactivate and end them, each step bounded. A failure is raised after."""
        missions = self.missions
        tasks = [asyncio.create_task(status.run(watchdog), name="status"),
                 asyncio.create_task(missions.command_loop(), name="ground-commands")]
        if guard is not None:
            tasks.append(asyncio.create_task(guard.run(), name="vision-loss"))
        if self.fly_mission:
            tasks.append(missions.start_mission())
        if self.on_active is not None:
            res = self.on_active(self)
            if asyncio.iscoroutine(res):
                tasks.append(asyncio.create_task(res, name="on-active"))
        failure: BaseException | None = None
        try:
            failure = await _stopped_or_failed(stop, tasks)
        finally:
            watch.arm()
            self.state = "stopping"
            self.notifier.stopping("stopping")
            await self._stop_flying(tasks)
        if failure is not None:
            raise failure

    async def _stop_flying(self, tasks: list[asyncio.Task[Any]]) -> None:
        """Hand the vehicle over (:meth:`deactivate`), then end the service's tasks, the flight
        task and the background landings; each step bounded, an overrun logged with the state."""
        ended, _ = await bounded(self.deactivate(), DEACTIVATE_TIMEOUT_S, "the hand-over (hold or land)")
        if not ended:
            self._stop_overran(f"the hand-over overran {DEACTIVATE_TIMEOUT_S:.0f} s")
        flight = self.missions.task
        everything = [*tasks, *([flight] if flight is not None else []), *self._background_tasks]
        if await stop_tasks(everything, TASK_STOP_TIMEOUT_S, "stopping the service's tasks"):
            self._stop_overran(f"stopping the service's tasks overran {TASK_STOP_TIMEOUT_S:.0f} s")

    def _record_perception(self, perception: PerceptionProcess) -> None:
        """Copy the stopped perception process's counters, timings and final map, and the
        latencies and localization summary, into the report."""
        counts = perception.counters()
        self.report.frames_processed = counts["processed"]
        self.report.frames_failed = counts["failed"]
        self.report.frames_unposed = counts["unposed"]
        self.report.frames_dropped = counts["dropped"]
        self.report.checkpoints = counts["checkpoints"]
        if perception.latest is not None:
            self.report.stage_timings = perception.latest.timings_summary
        self.report.latency = self.latency_summary()
        self.report.localization = self.localization.summary()
        if perception.final_map is not None:
            self.smap = perception.final_map

    def _pose_fresh(self) -> bool:
        """The planner's setpoints may be flown: PX4's position is fresh and, when PX4 flies
        on our SLAM pose, that pose has not been lost."""
        v = self.vehicle
        return (v is not None and v.snapshot().position_fresh(self.cfg.link.pose_timeout_s)
                and self.localization.pose_ok)

    def _obstacle_input(self) -> ObstacleDistanceInput | None:
        """The OBSTACLE_DISTANCE feed's input: the newest costmap around the vehicle."""
        v, perception = self.vehicle, self.perception
        if v is None or perception is None:
            return None
        try:
            costmap = perception.costmap()
        except MapError:
            return None  # no map yet: PX4 sees no feed rather than an empty one
        return ObstacleDistanceInput.from_vehicle_state(costmap, v.snapshot())

    def latency_summary(self) -> dict[str, dict[str, float | int]]:
        """End-to-end latencies so far, ``{"count", "p50_ms", "p95_ms", "max_ms"}`` each:

        * ``frame_to_map``: a frame's capture (read from the camera) until the costmap that
          includes it reaches the service (perception + map update + hand-over);
        * ``frame_to_setpoint``: a frame's capture until the first setpoint computed from a
          plan made on a costmap that includes it is handed to the setpoint stream (adds the
          wait for the next plan, planning and trajectory timing). Sampled once per plan.
        """
        out: dict[str, dict[str, float | int]] = {}
        if self.perception is not None:
            out["frame_to_map"] = LatencyStats(self.perception.frame_to_map_ms).summary()
        if self.runner is not None:
            out["frame_to_setpoint"] = LatencyStats(self.runner.frame_to_setpoint_ms).summary()
        return out

    @property
    def objects(self) -> tuple[ObjectFootprint, ...]:
        """The map's objects: the perception process's latest while running, else the map's."""
        if self.perception is not None and self.perception.latest is not None and self.state != "stopped":
            return self.perception.objects
        return self.smap.objects if self.smap is not None else ()

    def request_stop(self) -> None:
        """Ask :meth:`run` to deactivate and return (what SIGTERM does)."""
        if self._stop is not None:
            self._stop.set()

    async def deactivate(self) -> None:
        """Stop flying: cancel the mission, then hold or land (``service.on_sigterm``) while
        setpoints still stream, then stop streaming. The map is saved on the way out."""
        await self.missions.cancel()
        v = self.vehicle
        if v is not None and v.offboard.state.streams:
            land = self.cfg.service.on_sigterm == "land" or self.missions.perception_lost or self.missions.landing_here
            then = FlightMode.LAND if land else FlightMode.HOLD
            try:
                await v.offboard.release(then)
                log.info("stopping: vehicle handed to %s", then.name)
            except CompanionError as exc:
                log.error("stopping: could not switch to %s (%s); streaming ends, PX4's offboard-loss "
                          "failsafe takes over", then.name, exc)
                await v.offboard.release(None)
                return
            if then is FlightMode.LAND:
                # Exit (and let systemd count the stop done) once the vehicle is down.
                try:
                    await v.state.wait_for(lambda s: not s.in_air, LAND_WAIT_S, "the vehicle to land")
                    log.info("stopping: landed")
                except CompanionError as exc:
                    log.warning("stopping: %s; the autopilot goes on landing by itself", exc)

    def _background(self, coro: Any, name: str) -> None:
        task = asyncio.get_running_loop().create_task(coro, name=name)
        self._background_tasks.add(task)
        task.add_done_callback(self._background_tasks.discard)

    @property
    def path_xy_m(self) -> NDArray[np.float64]:
        """The latest planned path (K, 2), map frame."""
        return self.missions.path_xy_m


async def _stopped_or_failed(stop: asyncio.Event, tasks: list[asyncio.Task[Any]]) -> BaseException | None:
    """Wait for ``stop``; the first of ``tasks`` to fail ends the wait too (its error, logged,
    is returned). A task that ends normally (a hook, the mission) is no reason to stop."""
    stopped = asyncio.ensure_future(stop.wait())
    pending: set[asyncio.Future[Any]] = {stopped, *tasks}
    try:
        while True:
            done, pending = await asyncio.wait(pending, return_when=asyncio.FIRST_COMPLETED)
            if stopped in done:
                return None
            for task in done:
                exc = None if task.cancelled() else task.exception()
                if exc is not None:
                    name = task.get_name() if isinstance(task, asyncio.Task) else repr(task)
                    log.error("service task %r failed (%r): stopping the service", name, exc)
                    return exc
    finally:
        stopped.cancel()
