"""What the vehicle is asked to fly: the autopilot's mission, a goal or a ground command.

:class:`MissionControl` owns the one flight task at a time (the mission or a goal), the legs a
pause keeps, and the landing when perception or PX4's position source is gone. It answers the
ground link's commands (goal, mission start/pause/abort, hold/land) and publishes each planned
path. The legs themselves are flown by :class:`~companion.service.mission_runner.MissionRunner`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging

import numpy as np
from numpy.typing import NDArray

from companion.background import end_task
from companion.config import CompanionConfig
from companion.errors import MissionError
from companion.ground import MqttBridge
from companion.ground.schema import GoalCommand, MissionCommand, VehicleCommand, command_kind_of
from companion.mavlink.vehicle import Vehicle
from companion.px4 import FlightMode
from companion.service.mission_runner import Leg, MissionRunner, mission_legs, position_enu
from semmap.errors import CompanionError

log = logging.getLogger(__name__)

#: Longest wait for the vehicle to land and disarm after the mission's last leg.
DISARM_WAIT_S = 60.0
#: Longest wait for the MAVLink link before a mission is downloaded.
CONNECT_WAIT_S = 30.0


class MissionControl:
    """The flight task (mission or goal) of one service run and the ground commands that steer it.

    Built with the service; :meth:`bind` hands it the vehicle, the mission runner and the ground
    link once the service has opened them. ``land_after_mission``: land at the end of the mission (else hold in
    OFFBOARD).
    """

    def __init__(self, cfg: CompanionConfig, *, land_after_mission: bool = True) -> None:
        self.cfg = cfg
        self.land_after_mission = land_after_mission
        #: Set when the mission has ended (flown, failed or aborted), not by a pause.
        self.done = asyncio.Event()
        #: The mission's legs not flown yet (the first is the one in progress); kept by a pause.
        self.legs_left: list[Leg] = []
        #: True between a ``pause`` and the ``start`` that resumes the mission.
        self.paused = False
        #: Set once perception could not be started again: the vehicle lands (stop included).
        self.perception_lost = False
        #: A landing where the vehicle is has been commanded (:meth:`land_here`): a stop keeps it.
        self.landing_here = False
        #: The last mission's failure, for the run's report.
        self.error: str | None = None
        #: The latest planned path (K, 2), map frame.
        self.path_xy_m: NDArray[np.float64] = np.zeros((0, 2))
        self._task: asyncio.Task[None] | None = None
        self._vehicle: Vehicle | None = None
        self._runner: MissionRunner | None = None
        self._ground: MqttBridge | None = None

    def bind(self, vehicle: Vehicle, runner: MissionRunner, ground: MqttBridge) -> None:
        """The parts the flights use, once the service has opened them."""
        self._vehicle, self._runner, self._ground = vehicle, runner, ground

    @property
    def busy(self) -> bool:
        """A mission or a goal is being flown."""
        return self._task is not None and not self._task.done()

    @property
    def task(self) -> asyncio.Task[None] | None:
        """The flight task (mission or goal) started last, ended or not."""
        return self._task

    def start_mission(self) -> asyncio.Task[None]:
        """Fly the autopilot's mission; returns its task (the service stops it with its loops)."""
        self.landing_here = False
        self._task = asyncio.create_task(self._mission(), name="mission")
        return self._task

    async def cancel(self) -> None:
        """Cancel the flight task and wait (bounded, :func:`~companion.background.end_task`) for it to end."""
        if self._task is not None:
            await end_task(self._task, "cancelling the flight task", log_error=True)

    def on_path(self, path_xy_m: NDArray[np.float64]) -> None:
        """A new planned path: kept and published to the ground station at the flight altitude."""
        self.path_xy_m = path_xy_m
        if self._ground is not None:
            z = np.full((len(path_xy_m), 1), self.cfg.planner.flight_altitude_m)
            self._ground.publish_path(np.hstack([path_xy_m, z]))

    async def land_here(self, why: str, lost: bool = False) -> None:
        """Stop the mission and land where the vehicle is: perception is gone for good
        (``lost``: the map cannot be trusted, a stop lands too), or PX4's position source is.
        The vehicle has been holding since its map or pose went stale."""
        self.perception_lost = self.perception_lost or lost
        # Set before the mission is cancelled: its end can stop the service, whose hand-over
        # must then keep this landing (a hold without a position source drifts).
        self.landing_here = True
        mission = self._task
        if mission is not None and not mission.done():
            # Cancelled now (it stops at its next await), awaited after the landing is commanded:
            # without a position source PX4 gives up its own estimate within seconds.
            mission.cancel()
        v = self._vehicle
        try:
            if v is None or not v.snapshot().in_air:
                log.error("%s: no mission or goal is flown until %s", why,
                          "the service restarts" if lost else "it is back and a mission is started")
                return
            log.error("%s: landing", why)
            try:
                if v.offboard.state.streams:
                    await v.offboard.release(FlightMode.LAND)
                else:
                    await v.commands.land()
            except CompanionError as exc:
                log.error("%s and landing could not be commanded (%s)", why, exc)
        finally:
            if mission is not None:
                await end_task(mission, "the flight task after a landing was commanded", log_error=True)

    # --- the mission and goals ----------------------------------------------------------

    async def _mission(self, resume: bool = False) -> None:
        """Fly the autopilot's mission (downloaded now), or with ``resume`` the legs a pause
        left; each leg is dropped from :attr:`legs_left` once flown (reached or given up)."""
        v, runner = self._vehicle, self._runner
        assert v is not None and runner is not None
        self.paused = False
        altitude_m = self.cfg.planner.flight_altitude_m
        try:
            await v.wait_connected(timeout_s=CONNECT_WAIT_S)
            if not resume:
                state = await v.state.wait_for(lambda s: s.home is not None and s.position_ned_m is not None,
                                               self.cfg.link.ready_timeout_s, "the home position")
                assert state.home is not None
                items = await v.download_mission()
                self.legs_left = mission_legs(items, state.home, altitude_m)
                log.info("mission: %d legs at %.2f m", len(self.legs_left), altitude_m)
            else:
                log.info("mission resumed: %d legs left", len(self.legs_left))
            await runner.take_off(altitude_m)
            while self.legs_left:
                runner.reports.append(await runner.fly_leg(self.legs_left[0]))
                self.legs_left.pop(0)
            if self.land_after_mission:
                await runner.finish(FlightMode.LAND)
                await v.state.wait_for(lambda s: not s.armed, DISARM_WAIT_S, "the vehicle to land and disarm")
        except CompanionError as exc:
            self.error = str(exc)
            log.error("mission: %s", exc)
            if v.offboard.state.streams:
                # The vehicle is still ours: hand it to PX4's Hold rather than keep streaming
                # setpoints for a mission that has ended.
                with contextlib.suppress(CompanionError):
                    await v.offboard.release(FlightMode.HOLD)
        finally:
            if not self.paused:
                self.done.set()

    async def _fly_goal(self, cmd: GoalCommand) -> None:
        v, runner, ground = self._vehicle, self._runner, self._ground
        assert v is not None and runner is not None and ground is not None
        altitude = cmd.altitude_m or self.cfg.planner.flight_altitude_m
        try:
            if not v.offboard.state.streams:
                await runner.take_off(altitude)
            rep = await runner.fly_leg(Leg(-1, (cmd.x_m, cmd.y_m), altitude))
            ground.publish_reply("goal", rep.reached, cmd.request_id,
                                 None if rep.reached else f"goal not reached ({rep.failed_plans} failed plans)")
        except CompanionError as exc:
            ground.publish_reply("goal", False, cmd.request_id, str(exc))

    # --- ground commands ----------------------------------------------------------------

    async def command_loop(self) -> None:
        """Answer the ground link's commands until cancelled; a refused one is answered with why."""
        ground = self._ground
        assert ground is not None
        async for cmd in ground.commands():
            log.info("ground command: %s", type(cmd).__name__)
            try:
                await self._handle(cmd)
            except CompanionError as exc:
                log.warning("ground command %s refused: %s", command_kind_of(cmd), exc)
                ground.publish_reply(command_kind_of(cmd), False, cmd.request_id, str(exc))

    async def _handle(self, cmd: GoalCommand | MissionCommand | VehicleCommand) -> None:
        v = self._vehicle
        assert v is not None
        busy = self.busy
        if isinstance(cmd, GoalCommand):
            if busy:
                raise MissionError("a mission or goal is being flown; abort it first")
            self.landing_here = False
            self._task = asyncio.create_task(self._fly_goal(cmd), name="goal")
        elif isinstance(cmd, MissionCommand):
            await self._mission_command(cmd.action, busy)
        elif isinstance(cmd, VehicleCommand):
            if busy:
                assert self._task is not None
                self._task.cancel()
            if v.offboard.state.streams:
                await v.offboard.release(FlightMode.LAND if cmd.action == "land" else FlightMode.HOLD)
            elif cmd.action == "land":
                await v.commands.land()
            else:
                await v.commands.hold()

    async def _mission_command(self, action: str, busy: bool) -> None:
        """``start`` (or resume after a pause), ``pause`` (hold here, keep the legs left) or
        ``abort`` (hold here, forget the mission). Raises :class:`MissionError` when the
        command does not fit the mission's state (answered on the reply topic)."""
        v = self._vehicle
        assert v is not None
        if action == "start":
            if busy:
                raise MissionError("a mission or goal is already being flown")
            resume = self.paused and bool(self.legs_left)
            self.done.clear()
            self.landing_here = False
            self._task = asyncio.create_task(self._mission(resume=resume), name="mission")
            return
        if not busy and not (action == "abort" and self.paused):
            raise MissionError(f"no mission is being flown to {action}")
        if busy:
            assert self._task is not None
            self.paused = action == "pause" and self._task.get_name() == "mission"
            await end_task(self._task, f"the flight task on a mission {action}", log_error=True)
        if action == "abort":
            self.paused = False
            self.legs_left = []
            self.done.set()
        pos = position_enu(v.snapshot())
        if pos is not None and v.offboard.state.streams and self._runner is not None:
            self._runner.hold_at(pos[:2], float(pos[2]))
        log.info("mission %s: holding at the current position%s", "paused" if action == "pause" else "aborted",
                 f" ({len(self.legs_left)} legs left)" if action == "pause" else "")


