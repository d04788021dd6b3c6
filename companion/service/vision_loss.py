"""What the service does when PX4's only position source, our SLAM pose, stops.

Indoors without GPS, PX4's EKF2 has a position only while our external vision reaches it;
without it EKF2 dead-reckons on the IMU and, ``EKF2_NOAID_TOUT`` (5 s) after the last fused
pose, declares its horizontal position invalid (``vehicle_local_position.xy_valid`` false,
LOCAL_POSITION_NED stops); its Land mode then falls back to Descend, which holds no position
and drifts. So the landing must *touch down* before that: :class:`EstimateLimits` holds the
two PX4 parameters it takes (``EKF2_NOAID_TOUT``, ``MPC_LAND_SPEED``) and gives the latest
time to command it from a height. :class:`VisionLossMonitor` is the I/O-free rule, stepped
with explicit times:

* no vision sent for ``hold_after_s`` while in the air -> ``HOLD``: the offboard setpoints
  stop following the planner and hold where PX4's last estimate puts the vehicle (the pose
  freshness the offboard failsafe reads is false, see :attr:`VisionLossMonitor.pose_ok`);
* vision back before the landing deadline -> ``RESUME``: the mission goes on from there;
* still none at the deadline -> ``LAND``: the mission is stopped and PX4 lands where it is.
  The deadline is the earlier of ``land_after_s`` (``link.vision_lost_land_s``, None: none)
  and the latest one PX4's estimate allows from the present height (a vehicle too high for
  a hold lands without one when the loss is noticed, after ``hold_after_s``).

:class:`VisionLossGuard` is the service's driver: it reads the two parameters from PX4 (and
follows their changes), refuses a ``link.vision_lost_land_s`` they cannot carry from the
flight altitude, steps the monitor a few times a second, logs each change and tells the
ground station with a STATUSTEXT, and commands the landing.
"""

from __future__ import annotations

import asyncio
import enum
import logging
import math
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

from companion.errors import CompanionError, LinkError
from companion.mavlink.link import MavlinkLink
from companion.mavlink.params import ParamWatch
from semmap.errors import ConfigError

log = logging.getLogger(__name__)

#: How often the guard looks at the vision stream.
GUARD_PERIOD_S = 0.1
#: STATUSTEXT holds 50 characters.
STATUSTEXT_LEN = 50


#: PX4's parameters the landing deadline is made of: EKF2's dead-reckoning limit (microseconds)
#: and its Land mode's descent speed (m/s).
NOAID_PARAM = "EKF2_NOAID_TOUT"
LAND_SPEED_PARAM = "MPC_LAND_SPEED"
#: Seconds kept between the touchdown and the end of PX4's estimate: the guard's period, the
#: LAND command's way through the service and PX4's Land reaching its descent speed, and the
#: height estimate's error (docs/mavlink.md gives what PX4 SITL took under load). The time
#: without vision counts from the last pose's capture, as PX4's timeout does.
LAND_MARGIN_S = 1.0
#: How often the guard asks again for parameters PX4 has not answered (seconds).
PARAM_RETRY_S = 2.0
#: PX4's optical-flow fusion switch (bit 0): without a flow sensor PX4 holds on its IMU alone
#: while our pose is lost, and its estimate does not see the vehicle drift.
FLOW_PARAM = "EKF2_OF_CTRL"
#: Times the guard asks for :data:`FLOW_PARAM` (a PX4 before v1.14 has none; it only warns).
FLOW_ASKS = 3


class VisionLossAction(enum.Enum):
    HOLD = "hold"
    RESUME = "resume"
    LAND = "land"


@dataclass(frozen=True)
class EstimateLimits:
    """How long PX4 keeps a horizontal position without our vision (``EKF2_NOAID_TOUT``, in
    seconds here) and how fast its Land mode descends (``MPC_LAND_SPEED``)."""

    noaid_timeout_s: float
    land_speed_m_s: float

    @classmethod
    def from_params(cls, values: dict[str, float]) -> EstimateLimits:
        """From PX4's parameter values (``EKF2_NOAID_TOUT`` in microseconds)."""
        noaid_us, speed = values[NOAID_PARAM], values[LAND_SPEED_PARAM]
        if not (math.isfinite(noaid_us) and noaid_us > 0.0 and math.isfinite(speed) and speed > 0.0):
            raise ConfigError(f"the autopilot's {NOAID_PARAM} ({noaid_us}) and {LAND_SPEED_PARAM} ({speed}) must be "
                              "> 0: without them no landing can be timed to end while PX4 still has a position")
        return cls(noaid_us * 1e-6, speed)

    def land_deadline_s(self, height_m: float, margin_s: float = LAND_MARGIN_S) -> float:
        """Seconds without vision by which a landing from ``height_m`` (above the floor) must be
        commanded to touch down ``margin_s`` before PX4 drops its position."""
        return self.noaid_timeout_s - margin_s - max(0.0, height_m) / self.land_speed_m_s


def check_land_after(land_after_s: float | None, hold_after_s: float, limits: EstimateLimits,
                     flight_altitude_m: float) -> float:
    """The landing deadline at ``flight_altitude_m`` (``planner.flight_altitude_m``); raises
    :class:`ConfigError` when a configured ``land_after_s`` (``link.vision_lost_land_s``)
    comes later, and warns when the vehicle would land there without holding first."""
    deadline = limits.land_deadline_s(flight_altitude_m)
    if land_after_s is not None and land_after_s > deadline:
        raise ConfigError(
            f"link.vision_lost_land_s ({land_after_s:g} s) lands too late: PX4 drops its position "
            f"{limits.noaid_timeout_s:g} s after our last pose ({NOAID_PARAM}), and the descent from "
            f"planner.flight_altitude_m ({flight_altitude_m:g} m) at {LAND_SPEED_PARAM} "
            f"({limits.land_speed_m_s:g} m/s) plus {LAND_MARGIN_S:g} s must end before that: the landing must start "
            f"by {deadline:.2f} s. Set link.vision_lost_land_s to at most that (or null: as late as is safe), "
            f"or raise {NOAID_PARAM} or {LAND_SPEED_PARAM} on the autopilot")
    if deadline <= hold_after_s:
        log.warning("vision loss: at %.2f m PX4's position (%s %.1f s, %s %.2f m/s) lasts too short for a hold of "
                    "%.1f s (link.vision_lost_hold_s) before the landing: the vehicle lands without holding when the loss is noticed",
                    flight_altitude_m, NOAID_PARAM, limits.noaid_timeout_s, LAND_SPEED_PARAM,
                    limits.land_speed_m_s, hold_after_s)
    return deadline


class VisionLossMonitor:
    """The rule of the module docstring (seconds without external vision). ``land_after_s``:
    the configured deadline (None: PX4's alone); ``limits``: PX4's, the deadline from the
    height at each step (None: not known yet, then ``land_after_s`` or, without one, landing
    at ``hold_after_s``); ``default_height_m``: the height assumed when a step gives none."""

    def __init__(self, hold_after_s: float, land_after_s: float | None = None, *,
                 limits: EstimateLimits | None = None, default_height_m: float = 0.0) -> None:
        if not hold_after_s > 0.0 or (land_after_s is not None and land_after_s <= hold_after_s):
            raise ConfigError(f"vision loss: hold after {hold_after_s} s must be > 0 and shorter than land after "
                              f"{land_after_s} s (link.vision_lost_hold_s, link.vision_lost_land_s)")
        self.hold_after_s = hold_after_s
        self.land_after_s = land_after_s
        self.limits = limits
        self.default_height_m = default_height_m
        self.state: VisionLossAction | None = None  # None: vision flowing (or on the ground)
        self._lost_since_s: float | None = None
        #: Seconds without vision when the latest action was taken.
        self.lost_for_s = 0.0

    @property
    def pose_ok(self) -> bool:
        """False while holding or landing for want of vision: the planner's setpoints are not flown."""
        return self.state not in (VisionLossAction.HOLD, VisionLossAction.LAND)

    def deadline_s(self, height_m: float | None = None) -> float:
        """Seconds without vision at which to land from ``height_m`` (None: the default height)."""
        h = height_m if height_m is not None and math.isfinite(height_m) else self.default_height_m
        if self.limits is not None:
            px4 = self.limits.land_deadline_s(h)
            return px4 if self.land_after_s is None else min(px4, self.land_after_s)
        return self.land_after_s if self.land_after_s is not None else self.hold_after_s

    def step(self, now_s: float, vision_age_s: float | None, in_air: bool,
             height_m: float | None = None) -> VisionLossAction | None:
        """The action to take now (None: nothing changes). ``vision_age_s``: seconds since the
        last vision message went out (None: none yet); ``height_m``: above the floor."""
        if not in_air:
            # On the ground nothing flies on the estimate; a landing for want of vision is over.
            self.state, self._lost_since_s = None, None
            return None
        if vision_age_s is not None and vision_age_s < self.hold_after_s:
            self._lost_since_s = None
            if self.state is VisionLossAction.HOLD:
                self.state = VisionLossAction.RESUME
                return self.state
            return None
        if self._lost_since_s is None:
            self._lost_since_s = now_s - (vision_age_s if vision_age_s is not None else 0.0)
        self.lost_for_s = now_s - self._lost_since_s
        if self.state is VisionLossAction.LAND:
            return None
        if self.lost_for_s >= self.deadline_s(height_m):
            self.state = VisionLossAction.LAND
            return self.state
        if self.lost_for_s >= self.hold_after_s and self.state is not VisionLossAction.HOLD:
            self.state = VisionLossAction.HOLD
            return self.state
        return None


def send_statustext(link: MavlinkLink, severity: int, text: str) -> bool:
    """A STATUSTEXT from us (PX4 forwards it to the ground station); False when not sent."""
    try:
        link.send(link.mav.statustext_encode(severity, text[:STATUSTEXT_LEN].encode("ascii", "replace")))
    except LinkError as exc:
        log.warning("STATUSTEXT %r not sent: %s", text, exc)
        return False
    return True


class VisionLossGuard:
    """Steps a :class:`VisionLossMonitor` every ``period_s`` (run :meth:`run` as a task).

    ``vision_age_s()``: seconds since the capture of our last new pose sent (None: none yet); ``in_air()``:
    the vehicle is flying; ``land()``: stop the mission and land (awaited once);
    ``height_m()``: the height above the floor (None: unknown). ``params``: PX4's
    ``EKF2_NOAID_TOUT`` and ``MPC_LAND_SPEED`` as they arrive (asked for until answered, then
    followed), which set the monitor's limits; the first complete pair is checked against
    the monitor's configured deadline at ``flight_altitude_m`` and :meth:`run` raises the
    :class:`ConfigError` of one it cannot carry (:func:`check_land_after`). ``flow_param``:
    PX4's :data:`FLOW_PARAM`; when it says PX4 fuses no optical flow the guard warns once
    (:attr:`flow_aided` False), since a hold then drifts on the IMU alone."""

    def __init__(self, monitor: VisionLossMonitor, link: MavlinkLink, vision_age_s: Callable[[], float | None],
                 in_air: Callable[[], bool], land: Callable[[], Awaitable[None]], *,
                 clock: Callable[[], float], period_s: float = GUARD_PERIOD_S,
                 height_m: Callable[[], float | None] | None = None, params: ParamWatch | None = None,
                 flight_altitude_m: float | None = None, flow_param: ParamWatch | None = None) -> None:
        self.monitor = monitor
        self.link = link
        self.vision_age_s = vision_age_s
        self.in_air = in_air
        self.land = land
        self.clock = clock
        self.period_s = period_s
        self.height_m = height_m
        self.params = params
        self.flight_altitude_m = monitor.default_height_m if flight_altitude_m is None else flight_altitude_m
        self._refusal: ConfigError | None = None
        if params is not None:
            params.on_change = self._on_param
        self.flow_param = flow_param
        #: PX4 fuses optical flow (None: not known yet, or PX4 did not say).
        self.flow_aided: bool | None = None
        if flow_param is not None:
            flow_param.on_change = self._on_flow_param
        #: Every action taken, as (clock s, action, seconds without vision).
        self.events: list[tuple[float, VisionLossAction, float]] = []

    def _on_param(self, name: str, value: float) -> None:
        assert self.params is not None
        if not self.params.complete:
            return
        first = self.monitor.limits is None
        try:
            limits = EstimateLimits.from_params(self.params.values)
            if first:
                deadline = check_land_after(self.monitor.land_after_s, self.monitor.hold_after_s, limits,
                                            self.flight_altitude_m)
                log.info("vision loss: PX4 keeps its position %.1f s without our pose (%s), lands at %.2f m/s (%s): "
                         "at %.2f m the landing starts %.2f s after the pose is lost", limits.noaid_timeout_s,
                         NOAID_PARAM, limits.land_speed_m_s, LAND_SPEED_PARAM, self.flight_altitude_m,
                         deadline if self.monitor.land_after_s is None else min(deadline, self.monitor.land_after_s))
            else:
                log.warning("vision loss: PX4's %s is now %g: landing deadlines follow", name, value)
        except ConfigError as exc:
            self._refusal = exc
            return
        self.monitor.limits = limits

    def _on_flow_param(self, name: str, value: float) -> None:
        aided = int(value) & 1 == 1
        if not aided and self.flow_aided is not False:
            log.warning("PX4 fuses no optical flow (%s %d): while our pose is lost it holds on its IMU alone, and "
                        "the vehicle drifts unseen (decimetres in seconds); wire a downward flow sensor to PX4 and "
                        "set %s 1 (docs/mavlink.md)", name, int(value), name)
        self.flow_aided = aided

    async def run(self) -> None:
        detach = self.params.attach() if self.params is not None else None
        detach_flow = self.flow_param.attach() if self.flow_param is not None else None
        try:
            next_ask = -math.inf
            flow_asks = 0
            while True:
                if self._refusal is not None:
                    raise self._refusal
                if self.clock() >= next_ask:
                    asked = False
                    if self.params is not None and not self.params.complete:
                        self.params.request_missing()
                        asked = True
                    if self.flow_param is not None and not self.flow_param.complete and flow_asks < FLOW_ASKS:
                        self.flow_param.request_missing()
                        flow_asks += 1
                        asked = True
                    if asked:
                        next_ask = self.clock() + PARAM_RETRY_S
                await self.check()
                await asyncio.sleep(self.period_s)
        finally:
            for d in (detach, detach_flow):
                if d is not None:
                    d()

    async def check(self) -> VisionLossAction | None:
        now = self.clock()
        height = self.height_m() if self.height_m is not None else None
        action = self.monitor.step(now, self.vision_age_s(), self.in_air(), height)
        if action is None:
            return None
        lost = self.monitor.lost_for_s
        self.events.append((now, action, lost))
        deadline = self.monitor.deadline_s(height)
        if action is VisionLossAction.HOLD:
            log.warning("SLAM pose lost for %.1f s: holding on PX4's estimate, landing after %.1f s without it",
                        lost, deadline)
            send_statustext(self.link, mavlink.MAV_SEVERITY_WARNING, f"SLAM lost: holding, land in "
                            f"{max(0.0, deadline - lost):.0f}s")
        elif action is VisionLossAction.RESUME:
            log.warning("SLAM pose back: resuming")
            send_statustext(self.link, mavlink.MAV_SEVERITY_NOTICE, "SLAM back: resuming")
        else:
            log.error("SLAM pose lost for %.1f s (landing deadline %.1f s at %s m): landing", lost, deadline,
                      "?" if height is None else f"{height:.2f}")
            send_statustext(self.link, mavlink.MAV_SEVERITY_CRITICAL, f"SLAM lost {lost:.0f}s: landing")
            try:
                await self.land()
            except CompanionError as exc:
                log.error("SLAM lost and the landing could not be commanded: %s", exc)
        return action
