"""The offboard failsafe state machine: pure logic, stepped with explicit times.

:class:`OffboardFailsafe` decides, at every setpoint tick, what (if anything) we send to the
autopilot. It knows no sockets or clocks: the caller passes ``now_s``, the vehicle's
telemetry snapshot and the freshness of our pose and map, so tests drive it with a fake
clock. The rules:

* **Autopilot heartbeat lost** (older than ``heartbeat_timeout_s``) -> ``LINK_LOST``: stop
  commanding and log. Nothing re-engages by itself; only :meth:`start_engage` does.
* **A pilot or ground station switches out of OFFBOARD** while we are engaged ->
  ``YIELDED``: stop streaming and never ask for OFFBOARD again until told to.
* **Stale pose or stale map** -> ``HOLDING``: keep OFFBOARD but stream a fixed setpoint at
  the vehicle's current position (latched when the hold starts). Once both are fresh again
  the planner's setpoints are used again, but only one produced after the hold began: a
  setpoint computed from the stale inputs is never flown.
* **The autopilot's position jumps** (it moved over ``POSITION_JUMP_M`` farther between two
  reports than its velocity explains: the estimate was reset, as PX4 does when external
  vision comes back after a loss or jumps with a loop closure) -> ``HOLDING`` where the
  vehicle now is, with :attr:`OffboardFailsafe.position_reset` set: the setpoints were
  planned in the old estimate, and flying to them would be an unplanned straight line.
* **The vehicle does not follow** (farther than ``tracking_error_m`` from the setpoint we
  send for longer than ``tracking_timeout_s``: it is still on the ground, blocked, or another
  controller flies it) -> ``HOLDING`` the same way, with :attr:`OffboardFailsafe.tracking_fault`
  set, so the planner re-plans from where the vehicle is instead of dragging it on.

States in which setpoints stream: ``WARMUP`` (before and while OFFBOARD is requested),
``ACTIVE`` and ``HOLDING``.
"""

from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass

from companion.mavlink.state import Vec3, VehicleState
from companion.px4 import FlightMode

log = logging.getLogger(__name__)


class OffboardState(enum.Enum):
    """Where the offboard controller is."""

    IDLE = "idle"  # not commanding; never engaged or released on purpose
    WARMUP = "warmup"  # streaming, OFFBOARD requested or about to be
    ACTIVE = "active"  # in OFFBOARD, flying the planner's setpoints
    HOLDING = "holding"  # in OFFBOARD, holding position because pose or map is stale
    YIELDED = "yielded"  # someone else took the vehicle out of OFFBOARD; we stay quiet
    LINK_LOST = "link_lost"  # autopilot heartbeat lost; we stay quiet until told

    @property
    def streams(self) -> bool:
        return self in (OffboardState.WARMUP, OffboardState.ACTIVE, OffboardState.HOLDING)


@dataclass(frozen=True)
class PositionSetpoint:
    """A local NED position setpoint (metres) with optional yaw and velocity feed-forward.

    ``yaw_rad``: heading from north, clockwise; None lets PX4 keep its own.
    ``velocity_ned_m_s``: feed-forward velocity; None sends position only.
    """

    position_ned_m: Vec3
    yaw_rad: float | None = None
    velocity_ned_m_s: Vec3 | None = None

    def __post_init__(self) -> None:
        values = [*self.position_ned_m, *(self.velocity_ned_m_s or ())]
        if self.yaw_rad is not None:
            values.append(self.yaw_rad)
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"setpoint has a non-finite value: {self}")


@dataclass(frozen=True)
class Transition:
    """One state change, for logs and the status report."""

    at_s: float
    old: OffboardState
    new: OffboardState
    reason: str


#: How much farther than its velocity explains the reported position may move between two
#: reports before it counts as a reset of the estimate, not motion (metres).
POSITION_JUMP_M = 0.15
#: Reports farther apart than this are not compared (an acceleration over a long gap would
#: look like a jump).
POSITION_JUMP_MAX_GAP_S = 0.3


class OffboardFailsafe:
    """Chooses the setpoint to send each tick. See the module docstring for the rules."""

    def __init__(self, heartbeat_timeout_s: float, position_timeout_s: float,
                 tracking_error_m: float = math.inf, tracking_timeout_s: float = 2.0) -> None:
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.position_timeout_s = position_timeout_s
        self.tracking_error_m = tracking_error_m
        self.tracking_timeout_s = tracking_timeout_s
        #: Set when a hold was started because the vehicle did not follow its setpoints;
        #: cleared when the planner's setpoints are flown again.
        self.tracking_fault = False
        #: Set when a hold was started because the autopilot's position estimate jumped;
        #: cleared likewise.
        self.position_reset = False
        #: A jump not yet taken by :meth:`take_position_reset`.
        self._reset_untaken = False
        self._off_track_since_s: float | None = None
        self._last_report: tuple[float, tuple[float, float, float]] | None = None
        self.state = OffboardState.IDLE
        self.reason = "not engaged"
        self.transitions: list[Transition] = []
        self._setpoint: PositionSetpoint | None = None
        self._setpoint_s = -math.inf
        self._hold: PositionSetpoint | None = None
        self._hold_since_s = -math.inf
        self._last_sent: PositionSetpoint | None = None
        #: Set while *we* are switching the vehicle to another mode (see ``release``), so
        #: the mode change is not mistaken for a pilot taking over.
        self.release_pending = False

    # --- inputs ----------------------------------------------------------------------

    def set_setpoint(self, setpoint: PositionSetpoint, now_s: float) -> None:
        """The planner's latest setpoint (the slot the streamer reads)."""
        self._setpoint = setpoint
        self._setpoint_s = now_s

    @property
    def setpoint(self) -> PositionSetpoint | None:
        """The planner's latest setpoint."""
        return self._setpoint

    @property
    def hold(self) -> PositionSetpoint | None:
        """The latched hold setpoint while holding (or warming up with no plan), else None."""
        return self._hold

    def start_engage(self, now_s: float, vehicle: VehicleState) -> None:
        """Start streaming ahead of an OFFBOARD request (also the way out of YIELDED/LINK_LOST)."""
        self._hold = None
        if self._setpoint is None:
            # Nothing planned yet: stream 'stay where you are' so PX4 accepts OFFBOARD.
            self._latch_hold(now_s, vehicle)
        self._go(OffboardState.WARMUP, now_s, "engage requested")

    def engaged(self, now_s: float) -> None:
        """The autopilot reports OFFBOARD after our request."""
        if self.state is OffboardState.WARMUP:
            self._go(OffboardState.ACTIVE, now_s, "autopilot in OFFBOARD")

    def take_position_reset(self) -> bool:
        """True once for each jump of the position estimate: the caller re-plans from where the
        vehicle now is, and the plan it starts while the hold lasts does not re-plan again."""
        taken, self._reset_untaken = self._reset_untaken, False
        return taken

    def release(self, now_s: float, reason: str) -> None:
        """Stop commanding on purpose (we handed the vehicle to another mode)."""
        self._hold = None
        self.tracking_fault = False
        self.position_reset = False
        self._off_track_since_s = None
        self._go(OffboardState.IDLE, now_s, reason)

    # --- the tick --------------------------------------------------------------------

    def step(
        self, now_s: float, vehicle: VehicleState, pose_fresh: bool, map_fresh: bool
    ) -> PositionSetpoint | None:
        """Apply the rules at ``now_s``; returns the setpoint to send now, or None."""
        st = self.state
        if st in (OffboardState.IDLE, OffboardState.YIELDED, OffboardState.LINK_LOST):
            return None
        if not vehicle.heartbeat_fresh(self.heartbeat_timeout_s):
            age = vehicle.heartbeat_age_s
            self._go(OffboardState.LINK_LOST, now_s,
                     "autopilot heartbeat lost" + (f" ({age:.1f} s old)" if age is not None else ""),
                     level=logging.ERROR)
            return None
        in_offboard = vehicle.flight_mode is FlightMode.OFFBOARD
        if st in (OffboardState.ACTIVE, OffboardState.HOLDING) and not in_offboard:
            if self.release_pending:
                return None
            mode = vehicle.flight_mode.name if vehicle.flight_mode else "an unknown mode"
            self._go(OffboardState.YIELDED, now_s,
                     f"vehicle switched to {mode} by someone else; yielding control",
                     level=logging.WARNING)
            return None
        fresh = pose_fresh and map_fresh
        jump_m = self._position_jump_m(now_s, vehicle)
        off_track = self._off_track_s(now_s, vehicle) if st is OffboardState.ACTIVE else None
        if jump_m is not None and jump_m > POSITION_JUMP_M and st in (OffboardState.ACTIVE, OffboardState.HOLDING):
            self._latch_hold(now_s, vehicle)
            self.position_reset = True
            self._reset_untaken = True
            self._off_track_since_s = None
            self._go(OffboardState.HOLDING, now_s, f"position estimate jumped {jump_m:.2f} m: holding where "
                     "the vehicle now is", level=logging.WARNING)
        elif st is OffboardState.ACTIVE and not fresh:
            what = " and ".join(n for n, ok in (("pose", pose_fresh), ("map", map_fresh)) if not ok)
            self._latch_hold(now_s, vehicle)
            self._go(OffboardState.HOLDING, now_s, f"stale {what}: holding position",
                     level=logging.WARNING)
        elif off_track is not None and off_track >= self.tracking_timeout_s:
            self._latch_hold(now_s, vehicle)
            self.tracking_fault = True
            self._go(OffboardState.HOLDING, now_s,
                     f"vehicle not following its setpoints (over {self.tracking_error_m:.2f} m away "
                     f"for {off_track:.1f} s): holding position", level=logging.WARNING)
        elif st is OffboardState.HOLDING and fresh and self._setpoint_s > self._hold_since_s:
            self._hold = None
            self.tracking_fault = False
            self.position_reset = False
            self._off_track_since_s = None
            self._go(OffboardState.ACTIVE, now_s, "pose and map fresh again: resuming")
        sp = self._choose()
        if sp is not None:
            self._last_sent = sp
        return sp

    def _position_jump_m(self, now_s: float, vehicle: VehicleState) -> float | None:
        """How much farther (horizontally) the reported position moved since the previous
        report than the reported velocity explains; None without two reports to compare.

        Reports are timed by the autopilot's own stamp where it has one: reports that queued up
        behind a stall of our loop arrive together, and timed by arrival a vehicle at speed
        would seem to jump."""
        pos, age = vehicle.position_ned_m, vehicle.position_age_s
        if pos is None or age is None:
            return None
        t = vehicle.position_boot_s if vehicle.position_boot_s is not None else now_s - age
        prev = self._last_report
        if prev is not None and abs(t - prev[0]) < 1e-3:
            return None  # the same report again
        self._last_report = (t, pos)
        # Also no comparison across a clock that went back (the autopilot rebooted).
        if prev is None or not 0.0 < t - prev[0] <= POSITION_JUMP_MAX_GAP_S:
            return None
        vn, ve, _ = vehicle.velocity_ned_m_s or (0.0, 0.0, 0.0)
        dt = t - prev[0]
        return math.hypot(pos[0] - prev[1][0] - vn * dt, pos[1] - prev[1][1] - ve * dt)

    def _off_track_s(self, now_s: float, vehicle: VehicleState) -> float | None:
        """How long the vehicle has been farther than ``tracking_error_m`` from the setpoint
        last sent (None while it is near it, or nothing can be judged)."""
        sp = self._last_sent
        if (sp is None or vehicle.position_ned_m is None
                or not vehicle.position_fresh(self.position_timeout_s)):
            self._off_track_since_s = None
            return None
        if math.dist(sp.position_ned_m, vehicle.position_ned_m) <= self.tracking_error_m:
            self._off_track_since_s = None
            return None
        if self._off_track_since_s is None:
            self._off_track_since_s = now_s
        return now_s - self._off_track_since_s

    def _choose(self) -> PositionSetpoint | None:
        if self.state is OffboardState.HOLDING:
            return self._hold
        if self._hold is not None:
            # A hold latched at engage time (nothing planned yet) lasts until the planner
            # produces a setpoint after it.
            if self._setpoint is None or self._setpoint_s <= self._hold_since_s:
                return self._hold
            self._hold = None
        return self._setpoint

    def _latch_hold(self, now_s: float, vehicle: VehicleState) -> None:
        """Hold at the vehicle's reported position, or the last setpoint if that is stale."""
        yaw = vehicle.yaw_ned_rad
        if vehicle.position_ned_m is not None and vehicle.position_fresh(self.position_timeout_s):
            pos = vehicle.position_ned_m
        elif self._last_sent is not None:
            pos = self._last_sent.position_ned_m
            yaw = self._last_sent.yaw_rad if yaw is None else yaw
        elif self._setpoint is not None:
            pos = self._setpoint.position_ned_m
        elif vehicle.position_ned_m is not None:
            pos = vehicle.position_ned_m
        else:
            self._hold = None
            return
        self._hold = PositionSetpoint(position_ned_m=pos, yaw_rad=yaw)
        self._hold_since_s = now_s

    def _go(self, new: OffboardState, now_s: float, reason: str, level: int = logging.INFO) -> None:
        old = self.state
        self.reason = reason
        if new is old:
            return
        self.state = new
        self.transitions.append(Transition(now_s, old, new, reason))
        log.log(level, "offboard %s -> %s: %s", old.value, new.value, reason)
