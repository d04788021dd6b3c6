"""The whole link stack as one async context manager, built from :class:`LinkConfig`.

:class:`Vehicle` opens the :class:`~companion.mavlink.link.MavlinkLink`, attaches the
:class:`~companion.mavlink.state.VehicleStateTracker`, and owns the command helpers, the
:class:`~companion.mavlink.offboard.OffboardController` (its setpoint task runs from the
start and is silent until ``engage()``), the optional OBSTACLE_DISTANCE feed and a watchdog
that logs when the autopilot's heartbeat is lost and when it comes back::

    async with Vehicle(cfg.link, is_map_fresh=semantic_map.is_fresh,
                       obstacle_source=lambda: obstacle_input) as vehicle:
        await vehicle.wait_connected(timeout_s=30.0)
        mission = await vehicle.download_mission()
        await vehicle.commands.arm()
        ...

Everything is closed in reverse order on exit, also when the body raises. Entering also asks
Linux for a short scheduler slice for the calling (event-loop) thread when
``cfg.scheduler_slice_ms`` is set (see :mod:`companion.mavlink.sched`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING

from pymavlink.dialects.v20 import common as mavlink

from companion.background import BackgroundTasks
from companion.errors import CommandError
from companion.mavlink.commands import CommandSender, VehicleCommands
from companion.mavlink.link import MavlinkLink
from companion.mavlink.mission_download import download_mission
from companion.mavlink.obstacle_distance import ObstacleDistanceFeed, ObstacleDistanceInput
from companion.mavlink.offboard import OffboardController
from companion.mavlink.sched import request_short_slice
from companion.mavlink.state import VehicleState, VehicleStateTracker
from companion.mavlink.timesync import AutopilotClock, TimesyncResponder
from companion.missions import MissionItemInt

if TYPE_CHECKING:
    from companion.config import LinkConfig

log = logging.getLogger(__name__)

#: How often the watchdog looks at the heartbeat age.
WATCHDOG_PERIOD_S = 0.2


class Vehicle:
    """Link, state, commands, offboard control and obstacle feed for one autopilot.

    ``is_pose_fresh``/``is_map_fresh``: freshness of our localisation and map (see
    :class:`OffboardController`). ``obstacle_source``: the OBSTACLE_DISTANCE input, or None
    for no feed (the feed also stays off when ``cfg.obstacle_distance_rate_hz`` is 0).
    ``record_path``: record the autopilot's telemetry to this ``.tlog``.
    """

    def __init__(
        self,
        cfg: LinkConfig,
        *,
        is_pose_fresh: Callable[[], bool] | None = None,
        is_map_fresh: Callable[[], bool] | None = None,
        obstacle_source: Callable[[], ObstacleDistanceInput | None] | None = None,
        record_path: str | Path | None = None,
    ) -> None:
        self.cfg = cfg
        self.link = MavlinkLink.from_config(cfg, record_path=record_path)
        self.state = VehicleStateTracker(cfg.target_system, cfg.target_component)
        self.commands = VehicleCommands(
            CommandSender(self.link, cfg.target_system, cfg.target_component,
                          timeout_s=cfg.command_timeout_s, retries=cfg.command_retries),
            self.state,
        )
        self.offboard = OffboardController(
            self.link, self.state, self.commands,
            rate_hz=cfg.setpoint_rate_hz,
            warmup_s=cfg.offboard_warmup_s,
            heartbeat_timeout_s=cfg.heartbeat_timeout_s,
            pose_timeout_s=cfg.pose_timeout_s,
            engage_timeout_s=cfg.offboard_engage_timeout_s,
            tracking_error_m=cfg.tracking_error_m,
            tracking_timeout_s=cfg.tracking_timeout_s,
            is_pose_fresh=is_pose_fresh,
            is_map_fresh=is_map_fresh,
        )
        #: Answers PX4's TIMESYNC requests (PX4 then fuses our vision at its capture time).
        self.timesync = TimesyncResponder(self.link, cfg.target_system)
        #: The autopilot's clock on ours (stamps of its telemetry), from our TIMESYNC requests.
        self.autopilot_clock = AutopilotClock(self.link, cfg.target_system)
        self.obstacle_feed: ObstacleDistanceFeed | None = None
        if obstacle_source is not None and cfg.obstacle_distance_rate_hz > 0:
            self.obstacle_feed = ObstacleDistanceFeed(
                self.link, obstacle_source, cfg.obstacle_distance_rate_hz,
                min_distance_m=cfg.obstacle_distance_min_m,
                max_distance_m=cfg.obstacle_distance_max_m,
            )
        self._stack: contextlib.AsyncExitStack | None = None
        self._background = BackgroundTasks()
        self._connected = False

    async def __aenter__(self) -> "Vehicle":
        if self.cfg.scheduler_slice_ms > 0:
            request_short_slice(self.cfg.scheduler_slice_ms / 1000.0)
        async with contextlib.AsyncExitStack() as stack:
            await stack.enter_async_context(self.link)
            stack.callback(self.state.attach(self.link))
            # PX4 maps our vision timestamps onto its clock from our TIMESYNC answers.
            stack.callback(self.timesync.attach())
            stack.callback(self.autopilot_clock.attach())
            await stack.enter_async_context(self.offboard)
            if self.obstacle_feed is not None:
                await stack.enter_async_context(self.obstacle_feed)
            await self._background.open()
            self._background.start(self._watchdog(), name="heartbeat-watchdog")
            self._background.start(self.autopilot_clock.run(), name="timesync-requests")
            self._stack = stack.pop_all()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        stack, self._stack = self._stack, None
        try:
            await self._background.close()
        finally:
            if stack is not None:
                await stack.__aexit__(exc_type, exc, tb)

    @property
    def connected(self) -> bool:
        """True while the autopilot's heartbeat is younger than ``heartbeat_timeout_s``."""
        return self.snapshot().heartbeat_fresh(self.cfg.heartbeat_timeout_s)

    def snapshot(self) -> VehicleState:
        """The latest telemetry (see :class:`VehicleState`)."""
        return self.state.snapshot()

    async def wait_connected(self, timeout_s: float) -> VehicleState:
        """Wait for the autopilot's heartbeat; raises ``StateTimeoutError`` naming the URL.

        Once connected, asks for HOME_POSITION if it has not arrived yet (PX4 streams it
        slowly and takeoff altitudes are relative to it); a refusal is only logged.
        """
        state = await self.state.wait_for(
            lambda s: s.heartbeat_fresh(self.cfg.heartbeat_timeout_s), timeout_s,
            f"an autopilot heartbeat on {self.cfg.url} (system {self.cfg.target_system}, "
            f"component {self.cfg.target_component})",
        )
        if state.home is None:
            try:
                await self.commands.request_message(mavlink.MAVLINK_MSG_ID_HOME_POSITION)
            except CommandError as exc:
                log.warning("autopilot did not send HOME_POSITION on request: %s", exc)
        return state

    async def download_mission(self) -> tuple[MissionItemInt, ...]:
        """The autopilot's current mission (see :func:`download_mission`)."""
        return await download_mission(
            self.link, self.cfg.target_system, self.cfg.target_component,
            timeout_s=max(self.cfg.command_timeout_s, 0.5), retries=self.cfg.command_retries,
        )

    async def _watchdog(self) -> None:
        timeout_s = self.cfg.heartbeat_timeout_s
        while True:
            s = self.state.snapshot()
            fresh = s.heartbeat_fresh(timeout_s)
            if fresh and not self._connected:
                log.info("autopilot connected on %s (mode %s, %s)", self.cfg.url,
                         s.flight_mode.name if s.flight_mode else "unknown",
                         "armed" if s.armed else "disarmed")
            elif not fresh and self._connected:
                log.error("autopilot heartbeat lost on %s (last %.1f s ago)", self.cfg.url,
                          s.heartbeat_age_s or 0.0)
            self._connected = fresh
            await asyncio.sleep(WATCHDOG_PERIOD_S)
