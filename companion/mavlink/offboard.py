"""Offboard control: the fixed-rate setpoint task and the controller that engages OFFBOARD.

:class:`SetpointStreamer` is its own task: at a fixed rate (20-50 Hz) it asks a source
callable for the setpoint to send *now* and sends it as SET_POSITION_TARGET_LOCAL_NED. The
source only reads a slot, so the task never waits for the planner. Ticks are scheduled on
absolute ``time.monotonic()`` deadlines (``start + k * period``), so the rate does not drift
with processing time; a tick that is more than one period late is skipped, never bunched.

:class:`OffboardController` owns a streamer and an
:class:`~companion.mavlink.failsafe.OffboardFailsafe`. ``engage()`` streams for at least
``warmup_s`` (>= 1 s, PX4 rejects OFFBOARD without a setpoint stream) before requesting
OFFBOARD and keeps streaming while in it; the failsafe rules (link loss, pilot takeover,
stale pose/map) are applied at every tick::

    async with OffboardController(link, tracker, commands, rate_hz=30) as ctl:
        ctl.set_setpoint(PositionSetpoint((0.0, 0.0, -1.5), yaw_rad=0.0))
        await ctl.engage()
        ...
        await ctl.release(FlightMode.HOLD)
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType

from pymavlink.dialects.v20 import common as mavlink

from companion.background import BackgroundPart
from companion.errors import LinkError
from companion.mavlink.commands import VehicleCommands
from companion.mavlink.failsafe import OffboardFailsafe, OffboardState, PositionSetpoint, Transition
from companion.mavlink.link import MavlinkLink
from companion.mavlink.state import StateTimeoutError, VehicleState, VehicleStateTracker
from companion.px4 import FlightMode

log = logging.getLogger(__name__)

Clock = Callable[[], float]
SetpointSource = Callable[[], PositionSetpoint | None]

#: type_mask bits: acceleration and yaw rate are never commanded.
_IGNORE_ACCEL_YAWRATE = (
    mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
)
_IGNORE_VELOCITY = (
    mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE
)


def encode_setpoint(
    link: MavlinkLink, setpoint: PositionSetpoint, target_system: int, target_component: int
) -> mavlink.MAVLink_set_position_target_local_ned_message:
    """SET_POSITION_TARGET_LOCAL_NED (MAV_FRAME_LOCAL_NED) for a position setpoint."""
    mask = _IGNORE_ACCEL_YAWRATE
    vel = setpoint.velocity_ned_m_s
    if vel is None:
        mask |= _IGNORE_VELOCITY
        vel = (0.0, 0.0, 0.0)
    yaw = setpoint.yaw_rad
    if yaw is None:
        mask |= mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE
        yaw = 0.0
    n, e, d = setpoint.position_ned_m
    return link.mav.set_position_target_local_ned_encode(
        link.time_boot_ms(), target_system, target_component, mavlink.MAV_FRAME_LOCAL_NED,
        mask, n, e, d, vel[0], vel[1], vel[2], 0.0, 0.0, 0.0, yaw, 0.0,
    )


@dataclass(frozen=True)
class StreamerStats:
    """What the setpoint task did since it started."""

    ticks: int
    sent: int
    skipped_ticks: int  # ticks more than one period late, dropped instead of bunched
    first_sent_s: float | None  # monotonic time of the first setpoint sent
    last_sent_s: float | None


class SetpointStreamer(BackgroundPart):
    """Sends ``source()`` at ``rate_hz`` on absolute ``time.monotonic`` deadlines (async context manager).

    ``source`` returns the setpoint to send now, or None to send nothing this tick. It must
    not block. A failing source is logged and that tick sends nothing.
    """

    def __init__(
        self,
        link: MavlinkLink,
        rate_hz: float,
        source: SetpointSource,
        target_system: int = 1,
        target_component: int = mavlink.MAV_COMP_ID_AUTOPILOT1,
    ) -> None:
        if not 1.0 <= rate_hz <= 200.0:
            raise ValueError(f"setpoint rate must be 1..200 Hz (got {rate_hz})")
        self.link = link
        self.rate_hz = rate_hz
        self.period_s = 1.0 / rate_hz
        self.source = source
        self.target_system = target_system
        self.target_component = target_component
        super().__init__()
        self._ticks = 0
        self._sent = 0
        self._skipped = 0
        self._first_sent_s: float | None = None
        self._last_sent_s: float | None = None
        self.source_errors = 0
        #: Optional hook called with the send time of each setpoint (benchmarks, tests).
        self.on_sent: Callable[[float], None] | None = None

    def _start(self) -> None:
        self._background.start(self._run(), name="setpoint-streamer")

    @property
    def stats(self) -> StreamerStats:
        return StreamerStats(self._ticks, self._sent, self._skipped, self._first_sent_s,
                             self._last_sent_s)

    def reset_stats(self) -> None:
        """Forget the first/last send times (so a new warm-up is measured from now)."""
        self._first_sent_s = None
        self._last_sent_s = None

    async def _run(self) -> None:
        next_s = time.monotonic()
        while True:
            self._tick()
            next_s += self.period_s
            now = time.monotonic()
            if now - next_s > self.period_s:
                behind = int((now - next_s) / self.period_s)
                self._skipped += behind
                next_s += behind * self.period_s
            await asyncio.sleep(max(0.0, next_s - now))

    def _tick(self) -> None:
        self._ticks += 1
        try:
            sp = self.source()
        except Exception:
            # Nothing is sent (PX4's offboard-loss failsafe acts if this persists); log the
            # first failure with its traceback and then every 100th, not 50 a second.
            self.source_errors += 1
            if self.source_errors == 1 or self.source_errors % 100 == 0:
                log.exception("setpoint source failed (%d times); nothing sent this tick",
                              self.source_errors)
            return
        if sp is None or not self.link.is_open:
            return
        self.link.send(encode_setpoint(self.link, sp, self.target_system, self.target_component))
        now = time.monotonic()
        self._sent += 1
        if self._first_sent_s is None:
            self._first_sent_s = now
        self._last_sent_s = now
        if self.on_sent is not None:
            self.on_sent(now)


@dataclass(frozen=True)
class OffboardStatus:
    """The controller's state for status reports."""

    state: OffboardState
    reason: str
    setpoint: PositionSetpoint | None
    setpoints_sent: int
    transitions: tuple[Transition, ...]


def _always_fresh() -> bool:
    return True


class OffboardController:
    """Engages OFFBOARD and applies the failsafe rules at every setpoint tick.

    ``is_pose_fresh``/``is_map_fresh``: callables saying whether our localisation and map
    are fresh enough to fly the planner's setpoints; by default the pose check is the
    autopilot's LOCAL_POSITION_NED being younger than ``pose_timeout_s`` and the map is
    always fresh.
    """

    def __init__(
        self,
        link: MavlinkLink,
        tracker: VehicleStateTracker,
        commands: VehicleCommands,
        *,
        rate_hz: float = 30.0,
        warmup_s: float = 1.0,
        heartbeat_timeout_s: float = 3.0,
        pose_timeout_s: float = 0.5,
        engage_timeout_s: float = 3.0,
        tracking_error_m: float = math.inf,
        tracking_timeout_s: float = 2.0,
        is_pose_fresh: Callable[[], bool] | None = None,
        is_map_fresh: Callable[[], bool] | None = None,
        clock: Clock = time.monotonic,
    ) -> None:
        if warmup_s < 1.0:
            raise ValueError(f"offboard warm-up must be >= 1 s (got {warmup_s})")
        self.link = link
        self.tracker = tracker
        self.commands = commands
        self.warmup_s = warmup_s
        self.pose_timeout_s = pose_timeout_s
        self.engage_timeout_s = engage_timeout_s
        self._clock = clock
        self._is_pose_fresh = is_pose_fresh or self._telemetry_pose_fresh
        self._is_map_fresh = is_map_fresh or _always_fresh
        self.failsafe = OffboardFailsafe(heartbeat_timeout_s, pose_timeout_s, tracking_error_m, tracking_timeout_s)
        sender = commands.sender
        self.streamer = SetpointStreamer(
            link, rate_hz, self._tick, sender.target_system, sender.target_component
        )
        self._engage_lock = asyncio.Lock()
        #: When OFFBOARD was requested (clock seconds), each engage: PX4 switches after the
        #: request and reports it in a heartbeat up to a second later.
        self.mode_requests_s: list[float] = []

    async def __aenter__(self) -> "OffboardController":
        await self.streamer.__aenter__()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self.failsafe.state.streams:
            # Leaving while PX4 still flies our setpoints: it will fail over on setpoint loss
            # (COM_OF_LOSS_T); say so loudly.
            log.warning("offboard controller closed while %s; PX4's offboard-loss failsafe "
                        "takes over", self.failsafe.state.value)
        self.failsafe.release(self._clock(), "controller closed")
        await self.streamer.__aexit__(exc_type, exc, tb)

    # --- the slot and the tick -------------------------------------------------------

    def set_setpoint(self, setpoint: PositionSetpoint) -> None:
        """Replace the latest setpoint; the streamer sends it from its next tick on."""
        self.failsafe.set_setpoint(setpoint, self._clock())

    def _telemetry_pose_fresh(self) -> bool:
        return self.tracker.snapshot().position_fresh(self.pose_timeout_s)

    def _tick(self) -> PositionSetpoint | None:
        return self.failsafe.step(
            self._clock(), self.tracker.snapshot(), self._is_pose_fresh(), self._is_map_fresh()
        )

    @property
    def state(self) -> OffboardState:
        return self.failsafe.state

    def status(self) -> OffboardStatus:
        return OffboardStatus(
            state=self.failsafe.state,
            reason=self.failsafe.reason,
            setpoint=self.failsafe.setpoint,
            setpoints_sent=self.streamer.stats.sent,
            transitions=tuple(self.failsafe.transitions),
        )

    # --- engage and release ----------------------------------------------------------

    async def engage(self, ready: Callable[[VehicleState], bool] | None = None, ready_what: str = "",
                     ready_timeout_s: float = 0.0) -> None:
        """Stream for ``warmup_s``, request OFFBOARD and wait until the vehicle reports it.

        With ``ready``, OFFBOARD is requested only once ``ready(state)`` holds after the
        warm-up (still streaming; waited for up to ``ready_timeout_s``, ``ready_what`` naming
        it), so a condition checked before the warm-up is checked again right before the switch.

        Also the (only) way back after YIELDED or LINK_LOST. Raises :class:`LinkError`
        without a live autopilot or anything to stream, the command's
        :class:`~companion.errors.CommandError` if PX4 refuses, and
        :class:`~companion.mavlink.state.StateTimeoutError` if the mode never shows up; on any
        failure the controller goes back to IDLE (stops streaming).
        """
        async with self._engage_lock:
            vehicle = self.tracker.snapshot()
            if not vehicle.heartbeat_fresh(self.failsafe.heartbeat_timeout_s):
                raise LinkError("cannot engage offboard: no recent autopilot heartbeat")
            self.failsafe.start_engage(self._clock(), vehicle)
            try:
                await self._warm_up()
                if ready is not None:
                    await self.tracker.wait_for(lambda s: ready(s) or not self.failsafe.state.streams,
                                                ready_timeout_s, ready_what or "the vehicle to be ready for OFFBOARD")
                    self._check_still_engaging()
                log.info("requesting OFFBOARD after %d setpoints", self.streamer.stats.sent)
                self.mode_requests_s.append(self._clock())
                await self.commands.set_mode(FlightMode.OFFBOARD)
                await self.tracker.wait_for(
                    lambda s: s.flight_mode is FlightMode.OFFBOARD or not self.failsafe.state.streams,
                    self.engage_timeout_s, "the vehicle to report OFFBOARD",
                )
                self._check_still_engaging()
                self.failsafe.engaged(self._clock())
            except BaseException as exc:
                if self.failsafe.state is OffboardState.WARMUP:
                    self.failsafe.release(self._clock(), f"engage failed: {exc!r}")
                raise

    async def _warm_up(self) -> None:
        self.streamer.reset_stats()
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.warmup_s + self.engage_timeout_s
        while True:
            self._check_still_engaging()
            first = self.streamer.stats.first_sent_s
            if first is not None and time.monotonic() - first >= self.warmup_s:
                return
            if loop.time() > deadline:
                raise StateTimeoutError(
                    "offboard warm-up: no setpoint could be streamed "
                    "(no planner setpoint and no vehicle position to hold)"
                )
            await asyncio.sleep(self.streamer.period_s)

    def _check_still_engaging(self) -> None:
        st = self.failsafe.state
        if st is not OffboardState.WARMUP:
            raise LinkError(f"offboard engage aborted: {st.value} ({self.failsafe.reason})")

    async def release(self, then: FlightMode | None = FlightMode.HOLD) -> None:
        """Hand the vehicle to ``then`` (e.g. HOLD or LAND) and stop streaming.

        The mode is requested while setpoints still stream, so PX4 never sees a setpoint
        gap in OFFBOARD; if the request fails we keep streaming and re-raise. ``then=None``
        stops streaming without a mode change (PX4's offboard-loss failsafe acts).
        """
        if then is not None and self.failsafe.state.streams:
            self.failsafe.release_pending = True
            try:
                await self.commands.set_mode(then)
            finally:
                self.failsafe.release_pending = False
        self.failsafe.release(self._clock(), f"released to {then.name if then else 'nothing'}")

