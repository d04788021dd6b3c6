"""A SITL-free PX4 stand-in speaking MAVLink 2 over UDP, for tests and ``companion sim-autopilot``.

One UDP socket bound to ``local_port`` (PX4: 14580) sends every message to the configured
remote ports (PX4: 14540 for the onboard/API link, 14550 for a ground station) and to any
address that has sent it a packet, which is how PX4 learns a partner (see :mod:`.transport`).

Behaviour follows PX4 v1.16 where clients can observe it: heartbeats with PX4 custom
modes, the command protocol (acks within one physics tick, duplicates re-acked without
re-executing), parameters with byte-wise encoding, the mission protocol, offboard that is
refused in the air without a setpoint stream and takes the ``COM_OBL_RC_ACT`` failsafe when
setpoints stop for ``COM_OF_LOSS_T``, auto-disarm after landing (``COM_DISARM_LAND``) and when
not taking off after arming (``COM_DISARM_PRFLT``). Where PX4 surprises a naive client (local
origin below the floor, readiness delay, 1 Hz heartbeat, ...) the mock does the same, each
behaviour switchable in :class:`~.behaviour.Px4Behaviour`.

Faults for tests are set on :attr:`MockAutopilot.faults` while it runs.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from companion.background import end_task
from companion.errors import SimulationError
from companion.geo import GeoOrigin
from companion.px4 import FlightMode, decode_param_value, encode_param_value, param_id_str
from companion.sim.autopilot import offboard, telemetry
from companion.sim.autopilot.behaviour import (
    Px4Behaviour,
    Wobble,
    accept_target,
    ekf_origin,
    report_ned,
    report_state,
)
from companion.sim.autopilot.commands import PREVENTS_ARMING, CommandHandler
from companion.sim.autopilot.estimator import SimEstimator, T_map_body_of
from companion.sim.autopilot.gps_denied import GPS_DENIED_PARAMS, VisionAiding
from companion.sim.autopilot.guided import FollowTarget
from companion.sim.autopilot.mission_server import MissionItem, MissionServer
from companion.sim.autopilot.navigator import Navigator
from companion.sim.autopilot.params import ParamStore
from companion.sim.autopilot.timesync import PeerClock
from companion.sim.autopilot.transport import Faults, UdpEndpoint, sign_with
from companion.sim.autopilot.vehicle import (
    KinematicMulticopter,
    Target,
    VehicleLimits,
    VehicleState,
)
from companion.sim.odometry import OdometryDriftModel
from semmap.frames import Transform

log = logging.getLogger(__name__)

_LANDED = mavlink.MAV_LANDED_STATE_ON_GROUND
#: PX4's ``COM_OBL_RC_ACT`` values (6 terminate and 7 disarm stop the motors).
OFFBOARD_LOSS_ACTIONS = {0: FlightMode.POSCTL, 1: FlightMode.ALTCTL, 2: FlightMode.MANUAL,
                         3: FlightMode.RTL, 4: FlightMode.LAND, 5: FlightMode.HOLD}
MANUAL_MODES = frozenset({FlightMode.POSCTL, FlightMode.ALTCTL, FlightMode.MANUAL})
#: Mode names as PX4 words them in messages.
MODE_NAMES = {FlightMode.POSCTL: "Position", FlightMode.ALTCTL: "Altitude", FlightMode.RTL: "Return"}
#: A changed parameter is broadcast again this long after the set (PX4: at least 5 ms).
PARAM_CHANGE_BROADCAST_S = 0.02
#: MISSION_ITEM_REACHED is sent again this long after the first time.
REACHED_RESEND_S = 0.5


@dataclass(frozen=True)
class VisionSample:
    """An external-vision pose received (VISION_POSITION_ESTIMATE or ODOMETRY), NED."""

    stamp_s: float  # mock clock
    msg_type: str
    time_usec: int
    position_ned_m: tuple[float, float, float]
    q_wxyz: tuple[float, float, float, float]


@dataclass(frozen=True)
class FailsafeEvent:
    stamp_s: float
    reason: str
    action: FlightMode


class MockAutopilot:
    """The mock PX4. Use ``async with MockAutopilot(...) as ap:``.

    ``local_port=0`` binds an ephemeral port (see :attr:`local_port`); ``remote_ports`` are
    sent to on ``remote_host``. All positions are local NED metres around ``home``, where the
    vehicle starts on the floor facing ``start_yaw_rad`` (NED yaw, from north, clockwise).
    ``odometry_drift``: the reported pose drifts (None = it is the truth); ``vision_gain``:
    how strongly external vision corrects it (0 = received vision is recorded only).
    ``behaviour``: which of PX4's ways to follow (default: all, see :class:`Px4Behaviour`).
    ``gps_denied``: GPS off, the horizontal position only from the companion's external vision
    (:mod:`.gps_denied`; the parameters it sets can be overridden in ``params``), the odometry
    drifting as ``odometry_drift`` or, without one, the default drift.
    """

    def __init__(
        self,
        *,
        host: str = "127.0.0.1",
        local_port: int = 14580,
        remote_ports: Iterable[int] = (14540, 14550),
        remote_host: str = "127.0.0.1",
        home: GeoOrigin | None = None,
        system_id: int = 1,
        params: dict[str, float] | None = None,
        physics_rate_hz: float = 100.0,
        stream_rates_hz: dict[str, float] | None = None,
        seed: int = 0,
        start_yaw_rad: float = 0.0,
        odometry_drift: OdometryDriftModel | None = None,
        vision_gain: float = 0.0,
        behaviour: Px4Behaviour | None = None,
        gps_denied: bool = False,
    ) -> None:
        if physics_rate_hz <= 0:
            raise SimulationError(f"physics_rate_hz must be > 0 (got {physics_rate_hz})")
        unknown = set(stream_rates_hz or {}) - set(telemetry.STREAMS)
        if unknown:
            raise SimulationError(f"unknown telemetry streams {sorted(unknown)} "
                                  f"(known: {sorted(telemetry.STREAMS)})")
        self.host = host
        self.behaviour = behaviour or Px4Behaviour()
        self.home = home or GeoOrigin()
        #: The origin of the local frame the mock reports (PX4's EKF origin, below the floor).
        self.ekf_origin = ekf_origin(self.home, self.behaviour.floor_z_ned_m)
        self.system_id = system_id
        self.params = ParamStore({"MAV_SYS_ID": system_id, **(GPS_DENIED_PARAMS if gps_denied else {}),
                                  **(params or {})})
        if gps_denied and odometry_drift is None:
            odometry_drift = OdometryDriftModel(seed=seed)  # dead reckoning between vision samples drifts
        self.faults = Faults()
        self._dt_s = 1.0 / physics_rate_hz
        self._mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=1)
        self._link = UdpEndpoint(self._mav, host, local_port,
                                 [(remote_host, int(p)) for p in remote_ports], self.faults,
                                 self._on_message, seed)
        self._task: asyncio.Task[None] | None = None
        self._t0 = time.monotonic()
        self._tick_monotonic_s = self._t0
        self.vehicle = KinematicMulticopter(self._limits_from_params(), yaw_rad=start_yaw_rad)
        #: What the mock reports and flies by: the truth through ``odometry_drift``, corrected
        #: by external vision (see :mod:`.estimator`).
        self.estimator = SimEstimator(odometry_drift, vision_gain)
        #: External vision as the only horizontal aiding while GPS is off (see :mod:`.gps_denied`).
        self.aiding = VisionAiding(self.params, self.estimator, seed)
        self._mode = FlightMode.HOLD
        self._mode_after_disarm = FlightMode.HOLD
        #: How far the reported height is above the true one (``Px4Behaviour.hold_sink_m_s``).
        self.height_error_m = 0.0
        self._armed = False
        self._armed_at_s = 0.0
        self._has_flown = False
        self._landed_since_s: float | None = 0.0
        self.landed_state = _LANDED
        self.missions = MissionServer(self._mav, self.send, self._on_mission_changed,
                                      self._on_set_current)
        self.missions.reject_seq = lambda: self.faults.reject_mission_seq
        self.navigator = Navigator(self.vehicle, self.params, self.home, self.set_mode,
                                   self._on_item_reached, self._on_current_changed,
                                   null_island_items=self.behaviour.null_island_items,
                                   land_brake_accel_m_s2=self.behaviour.land_brake_accel_m_s2)
        self.navigator.enter(FlightMode.HOLD)
        self.commands = CommandHandler(self)
        # offboard
        self._last_setpoint_s = -math.inf
        self._offboard_target: Target | None = None
        self.setpoints: deque[offboard.ReceivedSetpoint] = deque(maxlen=2000)
        #: The longest time without a setpoint while in OFFBOARD (s): between two setpoints, or
        #: from the last one until OFFBOARD ended (a stream that never resumed counts too).
        self.offboard_gap_max_s = 0.0
        self.vision: deque[VisionSample] = deque(maxlen=2000)
        #: The companion's clock, learned from TIMESYNC (see :mod:`.timesync`).
        self.peer_clock = PeerClock()
        self._last_vision_stamp_s = -math.inf
        self.failsafes: list[FailsafeEvent] = []
        #: Since when PX4 descends without a horizontal position (None: it has one).
        self._blind_since: float | None = None
        self._blind_v0 = np.zeros(2)
        heading = float(np.random.default_rng(seed + 7).uniform(-math.pi, math.pi))
        self._blind_dir = np.array([math.cos(heading), math.sin(heading)])
        #: Every mode change as ``(mock clock s, new mode)``, for judging a flight afterwards.
        self.mode_changes: deque[tuple[float, FlightMode]] = deque(maxlen=1000)
        self.messages_received: Counter[str] = Counter()
        self.last_received: dict[str, Any] = {}
        self.peer_heartbeats: dict[tuple[int, int], float] = {}
        self.status_texts: deque[str] = deque(maxlen=200)
        self.reached_items: list[int] = []
        self._reached_resend: tuple[int, float] | None = None
        # telemetry schedule: name -> [interval_s or 0, next_due_s]
        rates = {name: rate for name, (_id, _enc, rate) in telemetry.STREAMS.items()}
        rates.update(stream_rates_hz or {})
        self._streams: dict[str, list[float]] = {
            n: [1.0 / r if r > 0 else 0.0, 0.0] for n, r in rates.items()}
        self._default_rates = dict(rates)
        #: Changed parameters to broadcast: (due on the mock clock, name).
        self._params_changed: deque[tuple[float, str]] = deque()
        self._battery_pct = 100.0
        self._wobble = Wobble(self.behaviour.wobble_m, seed)
        #: Received offboard targets waiting out ``tracking_delay_s``: (apply at s, target).
        self._delayed_targets: deque[tuple[float, Target]] = deque()
        #: Injected failures (MAV_CMD_INJECT_FAILURE): (FAILURE_UNIT, instance) -> FAILURE_TYPE.
        self.failures: dict[tuple[int, int], int] = {}
        #: PX4's pre-flight checks pass (EKF and GPS converged): arming allowed, home valid.
        self.ready = self.behaviour.ready_after_s <= 0.0

    # --- lifecycle -----------------------------------------------------------------------

    async def __aenter__(self) -> MockAutopilot:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    async def start(self) -> None:
        """Bind the socket and start the physics/telemetry loop."""
        await self._link.open()
        self._t0 = time.monotonic()
        self._tick_monotonic_s = self._t0
        self._task = asyncio.create_task(self._run(), name="mock-autopilot")
        log.info("mock autopilot (system %d) on udp %s:%d -> %s", self.system_id, self.host,
                 self.local_port, ", ".join(f"{h}:{p}" for h, p in self._link.remotes))

    async def stop(self) -> None:
        """Stop the loop and close the socket (idempotent)."""
        task, self._task = self._task, None
        try:
            await end_task(task, "the mock autopilot's loop")
        finally:
            self._link.close()

    async def serve_forever(self) -> None:
        """Run until cancelled (the CLI's main loop)."""
        if self._task is None:
            await self.start()
        assert self._task is not None
        await self._task

    @property
    def local_port(self) -> int:
        """The bound UDP port (useful with ``local_port=0``)."""
        return self._link.local_port

    def enable_signing(self, key: bytes, unsigned_from: tuple[tuple[str, int], ...] = ()) -> None:
        """MAVLink 2 signing with ``key``, as PX4 with ``MAV_SIGN_CFG`` set: everything sent is
        signed, unsigned or badly signed input is dropped (except from ``unsigned_from``)."""
        sign_with(self._mav, key)
        self._link.require_signed(key, unsigned_from)

    def add_remote(self, host: str, port: int) -> None:
        """Also stream to ``host:port`` from now on."""
        if (host, port) not in self._link.remotes:
            self._link.remotes.append((host, port))

    # --- state for tests and the simulator -----------------------------------------------

    def now_s(self) -> float:
        """Seconds since the mock started on its own clock (``clock_rate`` x wall clock), the
        clock of every stamp it sends or records."""
        return (time.monotonic() - self._t0) * self.behaviour.clock_rate

    def stamp_of_monotonic(self, monotonic_s: float) -> float:
        """A ``time.monotonic`` instant on the mock's clock (what TIMESYNC estimates)."""
        return (monotonic_s - self._t0) * self.behaviour.clock_rate

    @property
    def tick_monotonic_s(self) -> float:
        """When the latest physics tick ran, on ``time.monotonic`` (the instant of
        :meth:`poses_map_body`; the simulation clock ``stamp_s`` can lag it after a stall)."""
        return self._tick_monotonic_s

    @property
    def mode(self) -> FlightMode:
        return self._mode

    @property
    def armed(self) -> bool:
        return self._armed

    @property
    def in_air(self) -> bool:
        return self.landed_state != _LANDED

    @property
    def position_ned_m(self) -> tuple[float, float, float]:
        return self.vehicle.position_ned_m

    def state(self) -> VehicleState:
        return self.vehicle.state()

    def T_map_body(self) -> tuple[float, Transform]:  # noqa: N802 - frame names
        """``(stamp_s, T_map_body)``: the body pose in the map frame (ENU, origin = the local
        NED origin = ``home`` given at construction), stamped on the mock clock."""
        return self.vehicle.stamp_s, self.vehicle.T_map_body()

    def estimated_state(self) -> VehicleState:
        """The state as the mock reports it (drifting odometry, vision-corrected)."""
        return self.estimator.estimated(self.vehicle.state())

    def poses_map_body(self) -> tuple[float, Transform, Transform]:
        """``(stamp_s, T_map_body true, T_map_body estimated)`` at one instant: the simulated
        camera renders from the first and reports the second, as a real camera posed by the
        autopilot's telemetry would."""
        state = self.vehicle.state()
        return state.stamp_s, self.vehicle.T_map_body(), T_map_body_of(self.estimator.estimated(state))

    def T_odom_body(self) -> Transform:  # noqa: N802 - frame names
        """The body pose in the odometry frame: the drifting odometry alone, never corrected by
        vision (what dead reckoning the reported velocity and yaw rate gives; height, roll and
        pitch as estimated)."""
        state = self.estimator.estimated(self.vehicle.state())
        n, e, yaw = self.estimator.raw_pose_ned
        return T_map_body_of(replace(state, position_ned_m=(n, e, state.position_ned_m[2]), yaw_rad=yaw))

    @property
    def home_ned_m(self) -> tuple[float, float, float]:
        """Home in local NED: the origin at start, then wherever the vehicle last armed."""
        return self.navigator.home_ned_m

    def mission_items(self, mission_type: int = 0) -> list[MissionItem]:
        return self.missions.items(mission_type)

    async def wait_until(self, predicate: Callable[[], bool], timeout_s: float,
                         what: str = "condition") -> None:
        """Poll ``predicate`` every 20 ms; raise TimeoutError naming ``what`` on timeout."""
        deadline = time.monotonic() + timeout_s
        while not predicate():
            if time.monotonic() > deadline:
                raise TimeoutError(f"mock autopilot: timed out after {timeout_s} s waiting for "
                                   f"{what} (mode {self._mode.name}, armed {self._armed}, "
                                   f"position {self.position_ned_m})")
            await asyncio.sleep(0.02)

    def inject_garbage(self, n_bytes: int = 64) -> None:
        """Send ``n_bytes`` random bytes (including a MAVLink 2 start byte) to every peer."""
        self._link.send_raw(bytes([0xFD]) + self._link.random_bytes(n_bytes - 1))

    def announce(self, severity: int, text: str) -> None:
        """Log ``text`` and send it as STATUSTEXT (``MAV_SEVERITY_*``), as PX4 reports events."""
        level = logging.WARNING if severity <= mavlink.MAV_SEVERITY_WARNING else logging.INFO
        log.log(level, "%s", text)
        self.status_texts.append(text)
        if self._link.is_open:
            for chunk in telemetry.statustext_chunks(self._mav, severity, text):
                self.send(chunk)

    # --- mode and arming (used by the command handler and the navigator) ----------------

    def set_mode(self, mode: FlightMode, *, takeoff_alt_m: float | None = None,
                 hold_at_ned_m: tuple[float, float, float] | None = None,
                 failsafe: bool = False) -> None:
        """Switch mode unconditionally (checks live in the command handler); ``failsafe``: a
        failsafe action, which PX4 does not take as the user's choice of mode."""
        if mode is not self._mode:
            log.info("mode %s -> %s", self._mode.name, mode.name)
            self.mode_changes.append((self.now_s(), mode))
        self._mode = mode
        if not failsafe and mode not in PREVENTS_ARMING and mode is not FlightMode.TAKEOFF:
            self._mode_after_disarm = mode
        self.navigator.enter(mode, takeoff_alt_m=takeoff_alt_m, hold_at_ned_m=hold_at_ned_m)
        if mode is FlightMode.OFFBOARD:
            if self._offboard_target is not None:
                self.vehicle.set_target(self._offboard_target)
        elif not mode.is_auto:
            self.vehicle.hold_here()
        self._heartbeat_on_change()

    def arm(self) -> None:
        if not self._armed:
            log.info("armed")
        self._armed = True
        self._armed_at_s = self.now_s()
        if self.vehicle.on_ground:
            # PX4 sets home where it arms: RTL returns there, relative altitudes refer to it.
            self.navigator.home_ned_m = self.vehicle.position_ned_m
            self._send_now("HOME_POSITION")
        self._has_flown = False
        self._landed_since_s = None
        self.vehicle.motors_on = True
        if self._mode is FlightMode.MISSION or self._mode.is_auto:
            self.navigator.enter(self._mode)
        elif self._mode is not FlightMode.OFFBOARD:
            self.vehicle.hold_here()
        self._heartbeat_on_change()

    def disarm(self) -> None:
        if self._armed:
            log.info("disarmed")
        self._armed = False
        self.vehicle.motors_on = False
        if self.behaviour.mode_after_disarm and self._mode is not self._mode_after_disarm:
            # PX4 goes back to the last mode chosen that allows arming (UserModeIntention).
            self.set_mode(self._mode_after_disarm)
        self._heartbeat_on_change()

    def _heartbeat_on_change(self) -> None:
        # PX4 sends HEARTBEAT on its 1 Hz schedule only: a change is seen up to 1 s late.
        if self.behaviour.heartbeat_on_change:
            self._send_now("HEARTBEAT")

    def offboard_available(self) -> bool:
        """True when setpoints arrived within COM_OF_LOSS_T (PX4's offboard signal check)."""
        return self.now_s() - self._last_setpoint_s < self.params.get("COM_OF_LOSS_T")

    # --- the loop ------------------------------------------------------------------------

    async def _run(self) -> None:
        last = time.monotonic()
        next_tick = last
        while True:
            next_tick += self._dt_s
            delay = next_tick - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
            else:
                next_tick = time.monotonic()  # overloaded: don't try to catch up
                await asyncio.sleep(0)
            now = time.monotonic()
            dt = min(now - last, 0.1)
            last = now
            try:
                self._tick(dt)
            except Exception:  # keep the autopilot alive; a test sees the log
                log.exception("mock autopilot tick failed")

    def _tick(self, dt_s: float) -> None:
        now = self.now_s()
        self._tick_monotonic_s = self._t0 + now / self.behaviour.clock_rate
        # Physics steps at most 0.1 s after a stall; the state's stamp stays on our clock
        # (what TIMESYNC and the telemetry's time_boot_ms report).
        self._track(now)
        self.vehicle.step(dt_s, clock_s=now)
        self.estimator.update(self.vehicle.state(), armed=self._armed)
        self.navigator.tick(self.vehicle.stamp_s)
        self._sink_in_hold(dt_s)
        self.aiding.tick(now, airborne=self._armed and self.in_air)
        self._check_offboard(now)
        self._check_position(now)
        self._update_landed(now)
        self.missions.tick(now)
        if self._reached_resend is not None and now >= self._reached_resend[1]:
            self.send(self._mav.mission_item_reached_encode(self._reached_resend[0]))
            self._reached_resend = None
        if self._armed:
            self._battery_pct = max(0.0, self._battery_pct - dt_s * 100.0 / 1200.0)
        while self._params_changed and self._params_changed[0][0] <= now:
            self._send_param(self._params_changed.popleft()[1])
        if not self.ready and now >= self.behaviour.ready_after_s:
            self._become_ready()
        self._stream(now)
        if self.peer_clock.request_due(now):
            self.send(self._mav.timesync_encode(0, int(now * 1e9)))

    def _become_ready(self) -> None:
        self.ready = True
        self.announce(mavlink.MAV_SEVERITY_INFO, "Ready for takeoff!")
        self._send_now("HOME_POSITION")

    def _note_offboard_gap(self, now: float) -> None:
        if self._mode is FlightMode.OFFBOARD and math.isfinite(self._last_setpoint_s):
            self.offboard_gap_max_s = max(self.offboard_gap_max_s, now - self._last_setpoint_s)

    def _check_offboard(self, now: float) -> None:
        if self._mode is not FlightMode.OFFBOARD or not self._armed:
            return  # PX4's failsafes act only while armed
        self._note_offboard_gap(now)
        if now - self._last_setpoint_s > self.params.get("COM_OF_LOSS_T"):
            act = int(self.params.get("COM_OBL_RC_ACT"))
            if self.behaviour.offboard_loss_px4_actions:
                action = OFFBOARD_LOSS_ACTIONS.get(act, FlightMode.HOLD)
            else:
                action = {3: FlightMode.RTL, 4: FlightMode.LAND}.get(act, FlightMode.HOLD)
            if action is FlightMode.RTL and not self.in_air:
                action = FlightMode.HOLD
            disarm = self.behaviour.offboard_loss_px4_actions and act in (6, 7)  # terminate, disarm
            self.announce(mavlink.MAV_SEVERITY_WARNING, "Failsafe: offboard signal lost, "
                          + ("Disarm" if disarm else MODE_NAMES.get(action, action.name.title())))
            self.failsafes.append(FailsafeEvent(now, "offboard setpoint loss", action))
            self.set_mode(action, failsafe=True)
            if disarm:
                self.disarm()
            elif action in MANUAL_MODES:
                # No RC: nothing holds the sticks, PX4 descends until it detects the landing.
                n, e, _d = self.vehicle.position_ned_m
                self.vehicle.set_target(Target(position_ned_m=(n, e, math.nan),
                                               velocity_ned_m_s=(0.0, 0.0, self.params.get("MPC_LAND_SPEED"))))

    @property
    def position_ok(self) -> bool:
        """The estimator has a horizontal position (always with GPS; without, while vision aids it)."""
        return not self.aiding.active or self.aiding.position_valid(self.now_s())

    def _check_position(self, now: float) -> None:
        """GPS off and no vision for ``EKF2_NOAID_TOUT``: PX4 has no horizontal position, and
        its failsafe lands without one (Descend, reported as Land): level, no position
        control, drifting (:meth:`_descend_blind`) until vision comes back or it is down."""
        if not (self.aiding.active and self._armed and self.in_air):
            self._blind_since = None
            return
        if not self.aiding.position_lost(now):
            if self._blind_since is not None:
                self._blind_since = None
                self.navigator.enter(self._mode)  # a position again: Land holds where it is now
            return
        if self._blind_since is None:
            self._blind_since = now
            self._blind_v0 = np.array(self.vehicle.state().velocity_ned_m_s[:2], dtype=np.float64)
            self.announce(mavlink.MAV_SEVERITY_CRITICAL, "Failsafe: no local position, Land")
            self.failsafes.append(FailsafeEvent(now, "local position lost", FlightMode.LAND))
            if self._mode is not FlightMode.LAND:
                self.set_mode(FlightMode.LAND, failsafe=True)
        self._descend_blind(now)

    def _descend_blind(self, now: float) -> None:
        assert self._blind_since is not None
        accel = 9.81 * math.tan(math.radians(self.behaviour.blind_tilt_error_deg))
        v_xy = self._blind_v0 + self._blind_dir * accel * (now - self._blind_since)
        self.vehicle.set_target(Target(position_ned_m=(math.nan, math.nan, math.nan),
                                       velocity_ned_m_s=(float(v_xy[0]), float(v_xy[1]),
                                                         self.params.get("MPC_LAND_SPEED"))))

    def _wants_climb(self) -> bool:
        tgt = self.vehicle.target
        p = tgt.position_ned_m
        if p is not None and math.isfinite(p[2]) and p[2] < self.vehicle.position_ned_m[2] - 0.05:
            return True
        v = tgt.velocity_ned_m_s
        return v is not None and math.isfinite(v[2]) and v[2] < -0.05

    def _sink_in_hold(self, dt_s: float) -> None:
        """PX4's Hold flies a height estimate that creeps up: the true hold point sinks while
        the reported height stays (``Px4Behaviour.hold_sink_m_s``)."""
        b = self.behaviour
        if not self.in_air:
            self.height_error_m = 0.0
            return
        if b.hold_sink_m_s <= 0.0 or self._mode is not FlightMode.HOLD:
            return
        step = min(b.hold_sink_m_s * dt_s, b.hold_sink_max_m - self.height_error_m)
        if step > 0.0 and self.navigator.lower_hold(step):
            self.height_error_m += step

    @property
    def reported_floor_z_ned_m(self) -> float:
        """The local z the mock reports for the floor now (the estimate's height error included)."""
        return self.behaviour.floor_z_ned_m - self.height_error_m

    def _update_landed(self, now: float) -> None:
        on_ground = (not self._armed) or (self.vehicle.on_ground and not self._wants_climb())
        if on_ground:
            self.landed_state = _LANDED
            if self._landed_since_s is None:
                self._landed_since_s = now
                if self._armed and self._has_flown:
                    self.announce(mavlink.MAV_SEVERITY_INFO, "Landing detected")
        else:
            self._landed_since_s = None
            if -self.vehicle.position_ned_m[2] > 0.1 and not self._has_flown:
                self._has_flown = True
                self.announce(mavlink.MAV_SEVERITY_INFO, "Takeoff detected")
            if self._mode is FlightMode.TAKEOFF:
                self.landed_state = mavlink.MAV_LANDED_STATE_TAKEOFF
            elif self._mode is FlightMode.LAND or (
                    self.vehicle.target.velocity_ned_m_s is not None
                    and self._mode.is_auto and self.vehicle.target.velocity_ned_m_s[2] > 0):
                self.landed_state = mavlink.MAV_LANDED_STATE_LANDING
            else:
                self.landed_state = mavlink.MAV_LANDED_STATE_IN_AIR
        if not self._armed or self._landed_since_s is None:
            return
        landed_for = now - self._landed_since_s
        if self._has_flown:
            limit = self.params.get("COM_DISARM_LAND")
            if limit > 0 and landed_for >= limit:
                self.announce(mavlink.MAV_SEVERITY_INFO, "Disarmed by landing")
                self.disarm()
                if self._mode in (FlightMode.LAND, FlightMode.RTL):
                    self.set_mode(FlightMode.HOLD)  # the naive autopilot's way
        else:
            limit = self.params.get("COM_DISARM_PRFLT")
            if limit > 0 and now - self._armed_at_s >= limit:
                self.announce(mavlink.MAV_SEVERITY_INFO, "Disarmed by auto preflight disarming")
                self.disarm()

    # --- telemetry -----------------------------------------------------------------------

    def snapshot(self) -> telemetry.Snapshot:
        now = self.now_s()
        health = telemetry.SENSORS_OK
        if self.faults.prearm_fail or not self.ready or not self.position_ok:
            health &= ~mavlink.MAV_SYS_STATUS_PREARM_CHECK
        for unit, _instance in self.failures:
            health &= ~telemetry.FAILURE_UNIT_SENSOR_BITS[unit]
        nav = self.navigator
        floor_z = self.behaviour.floor_z_ned_m
        return telemetry.Snapshot(
            time_boot_ms=int(now * 1000), time_usec=int(now * 1e6),
            vehicle=report_state(self.estimated_state(), self.reported_floor_z_ned_m), home=self.ekf_origin,
            home_ned_m=report_ned(self.navigator.home_ned_m, floor_z), mode=self._mode,
            armed=self._armed, landed_state=self.landed_state,
            sensors_health=health, mission_seq=nav.mission_seq, mission_total=nav.mission_count,
            mission_state=int(nav.mission_state), battery_remaining_pct=int(self._battery_pct),
            system_id=self.system_id,
            gps_fix=not any(u == mavlink.FAILURE_UNIT_SENSOR_GPS for u, _i in self.failures),
            range_down_m=-self.vehicle.position_ned_m[2])

    def _stream(self, now: float) -> None:
        snap: telemetry.Snapshot | None = None
        for name, sched in self._streams.items():
            interval, due = sched
            if interval <= 0 or now < due or (name == "HOME_POSITION" and not self.ready):
                continue
            if name == "LOCAL_POSITION_NED" and self._blind_since is not None:
                continue  # PX4 streams it only while xy_valid and v_xy_valid
            sched[1] = due + interval if now - due < interval else now + interval
            snap = snap or self.snapshot()
            self.send(telemetry.STREAMS[name][1](self._mav, snap))

    def _send_now(self, name: str) -> None:
        if self._link.is_open:
            self.send(telemetry.STREAMS[name][1](self._mav, self.snapshot()))

    def set_stream_interval(self, msg_id: int, interval_us: float) -> bool:
        """MAV_CMD_SET_MESSAGE_INTERVAL semantics; False if the message is not streamable."""
        for name, (mid, _enc, _rate) in telemetry.STREAMS.items():
            if mid == msg_id:
                if interval_us < 0:
                    self._streams[name][0] = 0.0
                elif interval_us == 0:
                    rate = self._default_rates[name]
                    self._streams[name][0] = 1.0 / rate if rate > 0 else 0.0
                else:
                    self._streams[name][0] = max(interval_us * 1e-6, self._dt_s)
                self._streams[name][1] = self.now_s()
                return True
        return False

    def stream_rate_hz(self, name: str) -> float:
        """Current rate of telemetry stream ``name`` (e.g. ``"ATTITUDE"``); 0 = off."""
        interval = self._streams[name][0]
        return 1.0 / interval if interval > 0 else 0.0

    def send_message_by_id(self, msg_id: int) -> bool:
        """Send one message now (MAV_CMD_REQUEST_MESSAGE); False if it is not available."""
        enc = telemetry.ON_REQUEST.get(msg_id)
        if enc is None:
            return False
        self.send(enc(self._mav, self.snapshot()))
        return True

    # --- link ----------------------------------------------------------------------------

    def send(self, msg: Any) -> None:
        """Encode ``msg`` (a pymavlink message) and send it to every peer."""
        self._link.send(msg)

    @property
    def bad_packets(self) -> int:
        """Datagrams or packets dropped as unparseable or unhandleable."""
        return self._link.bad_packets

    def _on_message(self, msg: Any) -> None:
        self._handle(msg)

    def _for_us(self, msg: Any) -> bool:
        ts = getattr(msg, "target_system", 0)
        return ts in (0, self.system_id)

    def _handle(self, msg: Any) -> None:
        mtype = msg.get_type()
        self.messages_received[mtype] += 1
        self.last_received[mtype] = msg
        if msg.get_srcSystem() == self.system_id and msg.get_srcComponent() == 1:
            return  # our own echo
        if not self._for_us(msg):
            return
        now = self.now_s()
        if mtype == "HEARTBEAT":
            self.peer_heartbeats[(msg.get_srcSystem(), msg.get_srcComponent())] = now
        elif mtype in ("COMMAND_LONG", "COMMAND_INT"):
            self.commands.handle(msg, now)
        elif self.missions.handle(msg, now):
            pass
        elif mtype in ("SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT",
                       "SET_ATTITUDE_TARGET"):
            self._on_setpoint(msg, now)
        elif mtype in ("VISION_POSITION_ESTIMATE", "ODOMETRY"):
            self._on_vision(msg, now)
        elif mtype == "PARAM_REQUEST_LIST":
            for i in range(len(self.params)):
                self._send_param(self.params.name_at(i) or "")
        elif mtype == "PARAM_REQUEST_READ":
            name = param_id_str(msg.param_id)
            if msg.param_index >= 0:
                name = self.params.name_at(msg.param_index) or ""
            if name in self.params:
                self._send_param(name)
            else:
                log.warning("PARAM_REQUEST_READ for unknown parameter %r", name)
        elif mtype == "PARAM_SET":
            self._on_param_set(msg)
        elif mtype == "TIMESYNC":
            self._on_timesync(msg, now)
        elif mtype == "FOLLOW_TARGET":
            self._on_follow_target(msg, now)

    def _on_timesync(self, msg: Any, now: float) -> None:
        """Answer a request on our clock; learn from an answer to ours (PX4's ``MavlinkTimesync``)."""
        if msg.tc1 == 0:
            self.send(self._mav.timesync_encode(int(now * 1e9), msg.ts1))
        else:
            self.peer_clock.add_answer(msg.ts1, msg.tc1, now)

    def _on_follow_target(self, msg: Any, now: float) -> None:
        """A target to follow (lat/lon degE7, alt AMSL, NED velocity), in Follow Target mode."""
        pos = self.home.to_ned(msg.lat * 1e-7, msg.lon * 1e-7, float(msg.alt))
        vel = tuple(float(v) for v in msg.vel)
        if not all(math.isfinite(v) for v in pos):
            log.warning("FOLLOW_TARGET with a non-finite position ignored")
            return
        if self.navigator.follow_target is None:
            self.navigator.follow_target = FollowTarget(pos, vel, now)  # type: ignore[arg-type]
        self.navigator.follow_target.update(pos, vel, now)  # type: ignore[arg-type]

    def _send_param(self, name: str) -> None:
        spec = self.params.spec(name)
        value = encode_param_value(self.params.get(name), spec.param_type)
        self.send(self._mav.param_value_encode(name.encode("ascii"), value, spec.param_type,
                                               len(self.params), self.params.index_of(name)))

    def _on_param_set(self, msg: Any) -> None:
        name = param_id_str(msg.param_id)
        if name not in self.params:
            log.warning("PARAM_SET for unknown parameter %r ignored", name)
            return
        spec = self.params.spec(name)
        if int(msg.param_type) != spec.param_type:
            # PX4 refuses a set whose type differs from the parameter's; it answers with the
            # unchanged value so the client sees the set did not take.
            log.warning("PARAM_SET %s: type %d does not match the parameter's type %d", name,
                        msg.param_type, spec.param_type)
        else:
            value = decode_param_value(msg.param_value, spec.param_type)
            if math.isfinite(value):
                old = self.params.get(name)
                if self.params.set(name, value) != old:
                    # PX4 broadcasts a changed parameter again shortly after (send_untransmitted).
                    self._params_changed.append((self.now_s() + PARAM_CHANGE_BROADCAST_S, name))
                self.vehicle.limits = self._limits_from_params()
            else:
                log.warning("PARAM_SET %s: non-finite value ignored", name)
        self._send_param(name)

    def _limits_from_params(self) -> VehicleLimits:
        p = self.params.get
        return VehicleLimits(
            max_speed_xy_m_s=p("MPC_XY_VEL_MAX"), max_speed_up_m_s=p("MPC_Z_VEL_MAX_UP"),
            max_speed_down_m_s=p("MPC_Z_VEL_MAX_DN"), max_accel_xy_m_s2=p("MPC_ACC_HOR"),
            max_accel_z_m_s2=p("MPC_ACC_UP_MAX"),
            max_yaw_rate_rad_s=math.radians(p("MPC_YAWRAUTO_MAX")))

    def _on_setpoint(self, msg: Any, now: float) -> None:
        mtype = msg.get_type()
        try:
            if mtype == "SET_POSITION_TARGET_LOCAL_NED":
                floor_z = self.reported_floor_z_ned_m
                est = report_state(self.estimated_state(), floor_z)
                target = accept_target(
                    offboard.target_from_local_ned(msg, est.position_ned_m, est.yaw_rad), floor_z)
            elif mtype == "SET_POSITION_TARGET_GLOBAL_INT":
                target = offboard.target_from_global_int(msg, self.home)
            else:
                target = offboard.target_from_attitude(msg, self.params.get("MPC_Z_VEL_MAX_UP"))
        except offboard.UnsupportedSetpointError as exc:
            log.warning("%s ignored: %s", mtype, exc)
            return
        # The controller flies the estimate to the setpoint: where the airframe really goes.
        target = self.estimator.to_true(target)
        frame = int(getattr(msg, "coordinate_frame", 0))
        self._note_offboard_gap(now)
        self.setpoints.append(offboard.ReceivedSetpoint(now, mtype, frame, int(msg.type_mask),
                                                        target))
        self._last_setpoint_s = now
        if self.behaviour.tracking_delay_s > 0.0:
            self._delayed_targets.append((now + self.behaviour.tracking_delay_s, target))
        else:
            self._apply_offboard_target(target)

    def _apply_offboard_target(self, target: Target) -> None:
        if self.behaviour.velocity_loop_lag:
            target = replace(target, velocity_gain_1_s=self.params.get("MPC_XY_VEL_P_ACC"))
        self._offboard_target = target
        if self._mode is FlightMode.OFFBOARD:
            self.vehicle.set_target(target)

    def _track(self, now: float) -> None:
        """PX4's tracking: offboard setpoints take effect late, the vehicle wobbles in the air."""
        while self._delayed_targets and self._delayed_targets[0][0] <= now:
            self._apply_offboard_target(self._delayed_targets.popleft()[1])
        flying = self.vehicle.motors_on and not self.vehicle.on_ground
        self.vehicle.target_offset_ned_m = self._wobble.offset_ned_m(now) if flying else np.zeros(3)

    def _on_vision(self, msg: Any, now: float) -> None:
        if msg.get_type() == "ODOMETRY":
            q = tuple(float(v) for v in msg.q)
            sample = VisionSample(now, "ODOMETRY", int(msg.time_usec),
                                  (float(msg.x), float(msg.y), float(msg.z)), q)  # type: ignore[arg-type]
            w, x, y, z = q
            yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
        else:
            q = telemetry.quaternion_wxyz(msg.roll, msg.pitch, msg.yaw)
            sample = VisionSample(now, "VISION_POSITION_ESTIMATE", int(msg.usec),
                                  (float(msg.x), float(msg.y), float(msg.z)), q)  # type: ignore[arg-type]
            yaw = float(msg.yaw)
        self.vision.append(sample)
        if not all(math.isfinite(v) for v in (*sample.position_ned_m[:2], yaw)):
            log.warning("%s with a non-finite pose ignored", sample.msg_type)
            return
        # EKF2 fuses the sample at its timestamp, the companion's clock mapped onto ours with
        # the TIMESYNC offset (MavlinkTimesync::sync_stamp); until that has converged, at its
        # arrival. A repeat of the last sample (the stream resends a pose until the next
        # camera frame) is not a new measurement.
        stamp_s = sample.time_usec * 1e-6
        if stamp_s <= self._last_vision_stamp_s:
            return
        self._last_vision_stamp_s = stamp_s
        stamp_ours = self.peer_clock.sync_stamp(stamp_s, now)
        n, e = sample.position_ned_m[0], sample.position_ned_m[1]
        if self.aiding.active:
            self.aiding.receive(now, stamp_ours, n, e, yaw)  # fused on EKF2's delayed horizon
        else:
            self.estimator.fuse_vision(stamp_ours, n, e, yaw)

    # --- mission callbacks ---------------------------------------------------------------

    def _on_mission_changed(self, mission_type: int) -> None:
        if mission_type == mavlink.MAV_MISSION_TYPE_MISSION:
            self.navigator.set_mission(self.missions.items(mission_type))
            self.reached_items.clear()
            first_m = self.navigator.first_waypoint_distance_m()
            if first_m is not None and first_m > self.params.get("MIS_DIST_1WP") > 0:
                # PX4's feasibility check warns and still accepts the mission.
                self.announce(mavlink.MAV_SEVERITY_WARNING, f"First waypoint far away from home: "
                              f"{first_m:.0f}m. Correct mission loaded?")

    def _on_set_current(self, seq: int) -> bool:
        ok = self.navigator.set_current(seq)
        if not ok:
            log.warning("set current mission item %d out of range", seq)
        return ok

    def _on_current_changed(self, seq: int) -> None:
        self._send_now("MISSION_CURRENT")

    def _on_item_reached(self, seq: int) -> None:
        log.info("mission item %d reached", seq)
        self.reached_items.append(seq)
        self.send(self._mav.mission_item_reached_encode(seq))
        # PX4 sends MISSION_ITEM_REACHED more than once: one lost packet must not leave a
        # client waiting forever for the end of a mission.
        self._reached_resend = (seq, self.now_s() + REACHED_RESEND_S)
        self._send_now("MISSION_CURRENT")
