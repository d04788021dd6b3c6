"""The vehicle's state as telemetry reports it: a frozen snapshot and the tracker that builds it.

:class:`VehicleStateTracker` listens on a :class:`~companion.mavlink.link.MavlinkLink` for
the autopilot's messages (only those from the target system/component, so a ground station's
heartbeat never counts as the autopilot's) and keeps the latest of each. ``snapshot()``
returns a :class:`VehicleState` with ages computed against the tracker's clock
(``time.monotonic`` unless a test injects one).

Frames: PX4 local NED (x north, y east, z down, metres), attitude as roll/pitch/yaw in
radians with yaw measured from north, clockwise. The service's map frame (:class:`MapFrame`)
is that frame in ENU with heights above home: PX4's local origin is where its estimator
started, not the floor (z reads -0.86 m on the ground with GPS height, +1.1 m with baro).
"""

from __future__ import annotations

import asyncio
import enum
import logging
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Protocol

from pymavlink.dialects.v20 import common as mavlink

from companion.errors import LinkError
from companion.px4 import FlightMode, decode_heartbeat
from semmap.frames import enu_to_ned, ned_to_enu

log = logging.getLogger(__name__)

Clock = Callable[[], float]
Vec3 = tuple[float, float, float]


class LandedState(enum.Enum):
    """``MAV_LANDED_STATE`` by name."""

    UNDEFINED = mavlink.MAV_LANDED_STATE_UNDEFINED
    ON_GROUND = mavlink.MAV_LANDED_STATE_ON_GROUND
    IN_AIR = mavlink.MAV_LANDED_STATE_IN_AIR
    TAKEOFF = mavlink.MAV_LANDED_STATE_TAKEOFF
    LANDING = mavlink.MAV_LANDED_STATE_LANDING

    @classmethod
    def from_mavlink(cls, value: int) -> "LandedState":
        try:
            return cls(value)
        except ValueError:
            return cls.UNDEFINED


@dataclass(frozen=True)
class HomePosition:
    """Where the vehicle will return to: global (WGS84, AMSL) and local NED coordinates."""

    latitude_deg: float
    longitude_deg: float
    altitude_amsl_m: float
    position_ned_m: Vec3


@dataclass(frozen=True)
class MapFrame:
    """The map frame: PX4's local frame in ENU (x east, y north) with z the height above the
    floor the vehicle took off from (home's floor). The map's heights (objects, the flight
    band) are heights above the floor, so every local position goes through here."""

    #: PX4's local z (NED) of the floor: where the vehicle stood, landed.
    floor_down_m: float

    def from_ned(self, north_m: float, east_m: float, down_m: float) -> Vec3:
        return ned_to_enu(north_m, east_m, down_m - self.floor_down_m)

    def to_ned(self, x_m: float, y_m: float, z_m: float) -> Vec3:
        n, e, d = enu_to_ned(x_m, y_m, z_m)
        return n, e, d + self.floor_down_m


@dataclass(frozen=True)
class GlobalPosition:
    """GLOBAL_POSITION_INT: WGS84 position, AMSL and relative-to-home altitude."""

    latitude_deg: float
    longitude_deg: float
    altitude_amsl_m: float
    relative_altitude_m: float


@dataclass(frozen=True)
class VehicleState:
    """A snapshot of the autopilot's telemetry. Fields are None until first reported.

    Ages are seconds since the last message of that kind, at snapshot time.
    """

    heartbeat_age_s: float | None
    armed: bool
    flight_mode: FlightMode | None
    landed_state: LandedState
    position_ned_m: Vec3 | None
    velocity_ned_m_s: Vec3 | None
    position_age_s: float | None
    attitude_rpy_rad: Vec3 | None
    battery_v: float | None
    battery_remaining: float | None  # fraction 0..1
    home: HomePosition | None
    global_position: GlobalPosition | None
    autopilot_system_status: int | None  # MAV_STATE
    #: PX4's pre-arm checks (SYS_STATUS ``MAV_SYS_STATUS_PREARM_CHECK``): None when the
    #: autopilot does not report them.
    prearm_ok: bool | None = None
    #: A downward range sensor's distance to what is below (DISTANCE_SENSOR, PITCH_270), and
    #: its age; None without one.
    range_down_m: float | None = None
    range_down_age_s: float | None = None
    #: PX4's local z (NED) of the floor: the vehicle's own z while it last stood landed (PX4
    #: moves home's z in flight, and home's z can differ from where the vehicle stands); home's
    #: z until the vehicle has been seen landed. None before either is known.
    floor_down_m: float | None = None
    #: The autopilot's time of the last LOCAL_POSITION_NED (its ``time_boot_ms``, seconds): when
    #: the estimate was made, which arrival times are not once reports queue up behind a stall.
    position_boot_s: float | None = None

    def heartbeat_fresh(self, timeout_s: float) -> bool:
        """True if the autopilot's heartbeat is younger than ``timeout_s``."""
        return self.heartbeat_age_s is not None and self.heartbeat_age_s <= timeout_s

    def position_fresh(self, timeout_s: float) -> bool:
        """True if LOCAL_POSITION_NED is younger than ``timeout_s``."""
        return self.position_age_s is not None and self.position_age_s <= timeout_s

    @property
    def yaw_ned_rad(self) -> float | None:
        """Heading from north, clockwise (radians), or None before the first ATTITUDE."""
        return None if self.attitude_rpy_rad is None else self.attitude_rpy_rad[2]

    @property
    def in_air(self) -> bool:
        return self.landed_state in (LandedState.IN_AIR, LandedState.TAKEOFF, LandedState.LANDING)

    @property
    def ready_to_arm(self) -> bool:
        """PX4's "Ready for takeoff": pre-arm checks pass (where reported), home is set and
        the estimator gives a local position."""
        return self.prearm_ok is not False and self.home is not None and self.position_ned_m is not None

    @property
    def map_frame(self) -> MapFrame | None:
        """The map frame, or None before the first HOME_POSITION (no height is known then)."""
        return None if self.floor_down_m is None else MapFrame(self.floor_down_m)

    @property
    def position_map_m(self) -> Vec3 | None:
        """The vehicle's position in the map frame (z above home), or None."""
        frame = self.map_frame
        if frame is None or self.position_ned_m is None:
            return None
        return frame.from_ned(*self.position_ned_m)

    @property
    def height_above_floor_m(self) -> float | None:
        pos = self.position_map_m
        return None if pos is None else pos[2]

    def clearance_below_m(self, max_age_s: float = 0.5) -> float | None:
        """How high the vehicle is by every height it has: above the floor, and the downward
        range sensor's reading where a fresh one exists (the lower of the two)."""
        height = self.height_above_floor_m
        fresh_range = (self.range_down_m is not None and self.range_down_age_s is not None
                       and self.range_down_age_s <= max_age_s)
        if height is None or not fresh_range:
            return height
        assert self.range_down_m is not None
        return min(height, self.range_down_m)


class StateTimeoutError(LinkError):
    """The vehicle did not reach the awaited state in time; the message says which."""


#: Everything the tracker reads.
TRACKED_MESSAGES: frozenset[str] = frozenset({
    "HEARTBEAT", "LOCAL_POSITION_NED", "ATTITUDE", "EXTENDED_SYS_STATE", "SYS_STATUS",
    "BATTERY_STATUS", "HOME_POSITION", "GLOBAL_POSITION_INT", "DISTANCE_SENSOR",
})

_UINT16_MAX = 0xFFFF


class VehicleStateTracker:
    """Keeps the autopilot's latest telemetry; feed it with :meth:`handle` or :meth:`attach`.

    ``target_system``/``target_component``: the autopilot's MAVLink address.
    """

    def __init__(
        self,
        target_system: int = 1,
        target_component: int = mavlink.MAV_COMP_ID_AUTOPILOT1,
        clock: Clock = time.monotonic,
    ) -> None:
        self.target_system = target_system
        self.target_component = target_component
        self._clock = clock
        self._heartbeat_s: float | None = None
        self._armed = False
        self._mode: FlightMode | None = None
        self._system_status: int | None = None
        self._prearm_ok: bool | None = None
        self._range_down: float | None = None
        self._range_s: float | None = None
        self._landed = LandedState.UNDEFINED
        self._pos: Vec3 | None = None
        self._vel: Vec3 | None = None
        self._pos_s: float | None = None
        self._pos_boot_s: float | None = None
        self._rpy: Vec3 | None = None
        self._battery_v: float | None = None
        self._battery_remaining: float | None = None
        self._home: HomePosition | None = None
        self._floor_down: float | None = None
        self._global: GlobalPosition | None = None
        self._changed = asyncio.Event()
        self._unknown_mode_logged: set[int] = set()

    def attach(self, link: "LinkLike") -> Callable[[], None]:
        """Register on ``link``; returns the function that detaches again."""
        return link.add_listener(self.handle, TRACKED_MESSAGES)

    def handle(self, msg: mavlink.MAVLink_message) -> None:
        """Update from one received message (ignores other senders and other types)."""
        if msg.get_srcSystem() != self.target_system or msg.get_srcComponent() != self.target_component:
            return
        mtype = msg.get_type()
        handler = _HANDLERS.get(mtype)
        if handler is not None:
            handler(self, msg)
            self._changed.set()

    # --- per-message updates ---------------------------------------------------------

    def _on_heartbeat(self, msg: mavlink.MAVLink_message) -> None:
        if msg.type == mavlink.MAV_TYPE_GCS or msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID:
            return
        decoded = decode_heartbeat(msg.base_mode, msg.custom_mode)
        if decoded.mode is None and msg.custom_mode not in self._unknown_mode_logged:
            self._unknown_mode_logged.add(msg.custom_mode)
            log.warning("autopilot reports unknown PX4 mode (main %d, sub %d)",
                        decoded.main_mode, decoded.sub_mode)
        if decoded.mode != self._mode:
            log.info("autopilot flight mode: %s -> %s",
                     self._mode.name if self._mode else None,
                     decoded.mode.name if decoded.mode else None)
        if decoded.armed != self._armed:
            log.info("autopilot %s", "armed" if decoded.armed else "disarmed")
        self._heartbeat_s = self._clock()
        self._armed = decoded.armed
        self._mode = decoded.mode
        self._system_status = msg.system_status

    def _on_local_position(self, msg: mavlink.MAVLink_message) -> None:
        self._pos = (float(msg.x), float(msg.y), float(msg.z))
        if self._landed is LandedState.ON_GROUND and math.isfinite(msg.z):
            self._floor_down = float(msg.z)  # standing on the floor: this z is the floor
        self._vel = (float(msg.vx), float(msg.vy), float(msg.vz))
        self._pos_s = self._clock()
        self._pos_boot_s = msg.time_boot_ms * 1e-3

    def _on_attitude(self, msg: mavlink.MAVLink_message) -> None:
        self._rpy = (float(msg.roll), float(msg.pitch), float(msg.yaw))

    def _on_extended_sys_state(self, msg: mavlink.MAVLink_message) -> None:
        self._landed = LandedState.from_mavlink(msg.landed_state)

    def _on_sys_status(self, msg: mavlink.MAVLink_message) -> None:
        bit = mavlink.MAV_SYS_STATUS_PREARM_CHECK
        if msg.onboard_control_sensors_present & bit:
            self._prearm_ok = bool(msg.onboard_control_sensors_health & bit)
        if msg.voltage_battery != _UINT16_MAX:
            self._battery_v = msg.voltage_battery / 1000.0
        if msg.battery_remaining >= 0:
            self._battery_remaining = msg.battery_remaining / 100.0

    def _on_battery_status(self, msg: mavlink.MAVLink_message) -> None:
        if msg.id != 0:  # the first battery is the one that powers the vehicle
            return
        cells_mv = [v for v in msg.voltages if v != _UINT16_MAX]
        cells_mv += [v for v in getattr(msg, "voltages_ext", ()) or () if v not in (0, _UINT16_MAX)]
        if cells_mv:
            self._battery_v = sum(cells_mv) / 1000.0
        if msg.battery_remaining >= 0:
            self._battery_remaining = msg.battery_remaining / 100.0

    def _on_distance_sensor(self, msg: mavlink.MAVLink_message) -> None:
        if msg.orientation != mavlink.MAV_SENSOR_ROTATION_PITCH_270:
            return  # not looking down
        d_cm = msg.current_distance
        if msg.min_distance <= d_cm <= msg.max_distance:
            self._range_down = d_cm / 100.0
            self._range_s = self._clock()

    def _on_home(self, msg: mavlink.MAVLink_message) -> None:
        self._home = HomePosition(
            latitude_deg=msg.latitude * 1e-7,
            longitude_deg=msg.longitude * 1e-7,
            altitude_amsl_m=msg.altitude / 1000.0,
            position_ned_m=(float(msg.x), float(msg.y), float(msg.z)),
        )

    def _on_global_position(self, msg: mavlink.MAVLink_message) -> None:
        self._global = GlobalPosition(
            latitude_deg=msg.lat * 1e-7,
            longitude_deg=msg.lon * 1e-7,
            altitude_amsl_m=msg.alt / 1000.0,
            relative_altitude_m=msg.relative_alt / 1000.0,
        )

    # --- reading ---------------------------------------------------------------------

    def snapshot(self) -> VehicleState:
        """The current state, with ages computed now."""
        now = self._clock()
        return VehicleState(
            heartbeat_age_s=None if self._heartbeat_s is None else now - self._heartbeat_s,
            armed=self._armed,
            flight_mode=self._mode,
            landed_state=self._landed,
            position_ned_m=self._pos,
            velocity_ned_m_s=self._vel,
            position_age_s=None if self._pos_s is None else now - self._pos_s,
            position_boot_s=self._pos_boot_s,
            attitude_rpy_rad=self._rpy,
            battery_v=self._battery_v,
            battery_remaining=self._battery_remaining,
            home=self._home,
            floor_down_m=self._floor_down if self._floor_down is not None else (
                None if self._home is None else self._home.position_ned_m[2]),
            global_position=self._global,
            autopilot_system_status=self._system_status,
            prearm_ok=self._prearm_ok,
            range_down_m=self._range_down,
            range_down_age_s=None if self._range_s is None else now - self._range_s,
        )

    async def wait_for(
        self,
        predicate: Callable[[VehicleState], bool],
        timeout_s: float,
        what: str,
        poll_s: float = 0.05,
    ) -> VehicleState:
        """Wait until ``predicate(snapshot)`` holds; raises :class:`StateTimeoutError` naming ``what``.

        Re-evaluates on every tracked message and at least every ``poll_s`` seconds (so
        age-based predicates such as 'heartbeat lost' also resolve).
        """
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while True:
            state = self.snapshot()
            if predicate(state):
                return state
            remaining = deadline - loop.time()
            if remaining <= 0:
                raise StateTimeoutError(f"timed out after {timeout_s:.1f} s waiting for {what}")
            self._changed.clear()
            try:
                async with asyncio.timeout(min(poll_s, remaining)):
                    await self._changed.wait()
            except TimeoutError:
                pass


class LinkLike(Protocol):
    """What :meth:`VehicleStateTracker.attach` needs of a link."""

    def add_listener(
        self, callback: Callable[[mavlink.MAVLink_message], None], msg_types: Iterable[str] | None = None
    ) -> Callable[[], None]: ...


_HANDLERS: dict[str, Callable[[VehicleStateTracker, mavlink.MAVLink_message], None]] = {
    "HEARTBEAT": VehicleStateTracker._on_heartbeat,
    "LOCAL_POSITION_NED": VehicleStateTracker._on_local_position,
    "ATTITUDE": VehicleStateTracker._on_attitude,
    "EXTENDED_SYS_STATE": VehicleStateTracker._on_extended_sys_state,
    "SYS_STATUS": VehicleStateTracker._on_sys_status,
    "BATTERY_STATUS": VehicleStateTracker._on_battery_status,
    "HOME_POSITION": VehicleStateTracker._on_home,
    "DISTANCE_SENSOR": VehicleStateTracker._on_distance_sensor,
    "GLOBAL_POSITION_INT": VehicleStateTracker._on_global_position,
}
