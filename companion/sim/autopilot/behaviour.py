"""Switches for the ways real PX4 differs from a naive autopilot, each on by default.

The mock autopilot behaves like PX4 v1.16 (SITL, measured) wherever a client can tell:
:class:`Px4Behaviour` names each such behaviour so a test about something else can turn one off
and say why, and :meth:`Px4Behaviour.naive` gives the old idealised autopilot. What each
switch means for a client is in docs/mock-autopilot.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np
from numpy.typing import NDArray

from companion.geo import GeoOrigin
from companion.sim.autopilot.vehicle import Target, VehicleState


@dataclass(frozen=True)
class Px4Behaviour:
    """PX4 behaviours of :class:`~companion.sim.autopilot.MockAutopilot` (defaults = PX4's)."""

    #: Local NED z the floor reads (EKF2 with GPS height: -0.86 m; 0.0 = origin on the floor).
    #: Only what the mock reports and accepts over MAVLink is in that frame; its truth
    #: (``state()``, ``position_ned_m``, ``T_map_body``) stays floor-based.
    floor_z_ned_m: float = -0.86
    #: Seconds from start until "Ready for takeoff!": before it the pre-arm health bit is
    #: clear, there is no home and arming is refused (0 = ready at once).
    ready_after_s: float = 3.0
    #: OFFBOARD requested during TAKEOFF is acknowledged but dropped: the take-off ends in Hold.
    offboard_during_takeoff_dropped: bool = True
    #: After a disarm the mode returns to the last one selected that allows arming (not Land,
    #: RTL or Takeoff): an offboard landing stays in Offboard. Arming is refused in Land and
    #: RTL and, as before, in Offboard without setpoints; a disarmed switch to Offboard is
    #: accepted without setpoints. Off: Land/RTL end in Hold, Offboard needs setpoints.
    mode_after_disarm: bool = True
    #: Send a HEARTBEAT at once on a mode or arming change (PX4 does not: False).
    heartbeat_on_change: bool = False
    #: Rate of the mock's clock (time_boot_ms, TIMESYNC, every stamp) against wall clock.
    clock_rate: float = 1.0
    #: ``COM_OBL_RC_ACT`` as PX4 reads it (0 Position, 1 Altitude, 2 Manual, 3 Return, 4 Land,
    #: 5 Hold); without RC the manual modes descend and land. Off: 0-2 mean Hold.
    offboard_loss_px4_actions: bool = True
    #: Offboard setpoints take effect this late (s), as PX4's controllers lag them.
    tracking_delay_s: float = 0.1
    #: The horizontal velocity loop is PX4's: acceleration ``MPC_XY_VEL_P_ACC`` (1.8 1/s) per
    #: m/s of velocity error, no acceleration feed-forward, so the vehicle trails a moving
    #: setpoint by about half a second and reaches a trajectory's end still moving. Off: the
    #: velocity follows at once within ``MPC_ACC_HOR``.
    velocity_loop_lag: bool = True
    #: Land engaged while moving brakes at this rate (m/s^2) and lands where the vehicle stops
    #: (PX4 SITL: 0.9 m on from 0.95 m/s); 0: it lands where Land was engaged.
    land_brake_accel_m_s2: float = 0.5
    #: Amplitude (m) of the seeded slow wobble about the setpoint while flying.
    wobble_m: float = 0.03
    #: Mission items without a position (lat/lon 0/0) are flown to 0/0, with PX4's warning
    #: about the first waypoint; off: 0/0 means "here".
    null_island_items: bool = True
    #: PX4's height estimate (EKF2, GPS height) creeps up while it holds in the air and Hold
    #: flies the estimate, so the vehicle sinks at this rate (m/s) while LOCAL_POSITION_NED
    #: and the altitudes stay put; the downward range finder (DISTANCE_SENSOR) shows the
    #: truth. 0 = the estimate is the truth.
    hold_sink_m_s: float = 0.05
    #: ... until the estimate is this much above the truth (m); on the ground it is true again.
    hold_sink_max_m: float = 0.1
    #: Without a horizontal position (no GPS, no vision for ``EKF2_NOAID_TOUT``) PX4's Land
    #: falls back to Descend: level attitude, no position control. The vehicle keeps the
    #: velocity it had and accelerates sideways by this attitude error (deg, in a seeded
    #: direction) while it descends at ``MPC_LAND_SPEED``.
    blind_tilt_error_deg: float = 1.5

    def __post_init__(self) -> None:
        if not self.clock_rate > 0.0:
            raise ValueError(f"Px4Behaviour.clock_rate must be > 0 (got {self.clock_rate})")
        for name in ("ready_after_s", "tracking_delay_s", "wobble_m", "land_brake_accel_m_s2", "hold_sink_m_s",
                     "hold_sink_max_m", "blind_tilt_error_deg"):
            value = getattr(self, name)
            if not value >= 0.0:
                raise ValueError(f"Px4Behaviour.{name} must be >= 0 (got {value})")

    @classmethod
    def naive(cls) -> Px4Behaviour:
        """The idealised autopilot the mock was before it learned PX4's ways."""
        return cls(floor_z_ned_m=0.0, ready_after_s=0.0, offboard_during_takeoff_dropped=False,
                   mode_after_disarm=False, heartbeat_on_change=True, clock_rate=1.0,
                   offboard_loss_px4_actions=False, tracking_delay_s=0.0, wobble_m=0.0,
                   null_island_items=False, velocity_loop_lag=False, land_brake_accel_m_s2=0.0,
                   hold_sink_m_s=0.0)


def behaviour_from_settings(settings: list[str], base: Px4Behaviour | None = None) -> Px4Behaviour:
    """``base`` (default: PX4's) with ``NAME=VALUE`` settings applied, e.g. ``ready_after_s=0``
    or ``heartbeat_on_change=true``. Raises ValueError naming the bad setting."""
    out = base or Px4Behaviour()
    types = {f.name: f.type for f in fields(Px4Behaviour)}
    for item in settings:
        name, sep, text = item.partition("=")
        if not sep or name not in types:
            raise ValueError(f"behaviour setting {item!r}: expected NAME=VALUE with NAME one of "
                             f"{', '.join(sorted(types))}")
        value: float | bool
        if types[name] in (bool, "bool"):
            if text.lower() not in ("true", "false", "1", "0", "on", "off"):
                raise ValueError(f"behaviour setting {name}: {text!r} is not true/false")
            value = text.lower() in ("true", "1", "on")
        else:
            try:
                value = float(text)
            except ValueError as exc:
                raise ValueError(f"behaviour setting {name}: {text!r} is not a number") from exc
        out = replace(out, **{name: value})
    return out


def report_ned(position_ned_m: tuple[float, float, float], floor_z_ned_m: float) -> tuple[float, float, float]:
    """A true (floor-based) local NED position in the frame the mock reports."""
    n, e, d = position_ned_m
    return (n, e, d + floor_z_ned_m)


def report_state(state: VehicleState, floor_z_ned_m: float) -> VehicleState:
    """A true (floor-based) state in the frame the mock reports."""
    if floor_z_ned_m == 0.0:
        return state
    return replace(state, position_ned_m=report_ned(state.position_ned_m, floor_z_ned_m))


def accept_target(target: Target, floor_z_ned_m: float) -> Target:
    """A setpoint in the reported frame carried to the floor-based frame the vehicle flies in."""
    pos = target.position_ned_m
    if pos is None or floor_z_ned_m == 0.0:
        return target
    return replace(target, position_ned_m=(pos[0], pos[1], pos[2] - floor_z_ned_m))


def ekf_origin(home: GeoOrigin, floor_z_ned_m: float) -> GeoOrigin:
    """The reported frame's origin (GPS_GLOBAL_ORIGIN): ``home`` is the floor below it."""
    return replace(home, alt_m=home.alt_m + floor_z_ned_m)


class Wobble:
    """A smooth seeded wobble about the setpoint: per axis three sinusoids of 0.1-0.7 Hz with
    random phases, peak ``amplitude_m`` horizontally and half that vertically."""

    def __init__(self, amplitude_m: float, seed: int) -> None:
        rng = np.random.default_rng(seed)
        self._freq_hz = rng.uniform(0.1, 0.7, (3, 3))
        self._phase_rad = rng.uniform(0.0, 2.0 * math.pi, (3, 3))
        self._amp_m = amplitude_m / 3.0 * np.array([[1.0], [1.0], [0.5]])

    def offset_ned_m(self, t_s: float) -> NDArray[np.float64]:
        """(3,) NED offset at time ``t_s``."""
        waves = np.sin(2.0 * math.pi * self._freq_hz * t_s + self._phase_rad)
        return np.asarray((self._amp_m * waves).sum(axis=1), dtype=np.float64)
