"""What the service does when PX4's only position source, our SLAM pose, stops.

Indoors without GPS, PX4's EKF2 has a position only while our external vision reaches it;
without it EKF2 dead-reckons on the IMU and, after ``EKF2_NOAID_TOUT`` (5 s), drops the
position altogether. :class:`VisionLossMonitor` is the I/O-free rule, stepped with explicit
times:

* no vision sent for ``hold_after_s`` while in the air -> ``HOLD``: the offboard setpoints
  stop following the planner and hold where PX4's last estimate puts the vehicle (the pose
  freshness the offboard failsafe reads is false, see :attr:`VisionLossMonitor.pose_ok`);
* vision back before ``land_after_s`` -> ``RESUME``: the mission goes on from there;
* still none after ``land_after_s`` -> ``LAND``: the mission is stopped and PX4 lands where
  it is, before its own estimate expires.

:class:`VisionLossGuard` is the service's driver: it steps the monitor a few times a second,
logs each change and tells the ground station with a STATUSTEXT, and commands the landing.
"""

from __future__ import annotations

import asyncio
import enum
import logging
from collections.abc import Awaitable, Callable

from pymavlink.dialects.v20 import common as mavlink

from companion.errors import CompanionError, LinkError
from companion.mavlink.link import MavlinkLink
from semmap.errors import ConfigError

log = logging.getLogger(__name__)

#: How often the guard looks at the vision stream.
GUARD_PERIOD_S = 0.1
#: STATUSTEXT holds 50 characters.
STATUSTEXT_LEN = 50


class VisionLossAction(enum.Enum):
    HOLD = "hold"
    RESUME = "resume"
    LAND = "land"


class VisionLossMonitor:
    """The rule of the module docstring. ``hold_after_s`` < ``land_after_s`` (seconds without
    external vision)."""

    def __init__(self, hold_after_s: float, land_after_s: float) -> None:
        if not 0.0 < hold_after_s < land_after_s:
            raise ConfigError(f"vision loss: hold after {hold_after_s} s must be > 0 and shorter than land after "
                              f"{land_after_s} s (link.vision_lost_hold_s, link.vision_lost_land_s)")
        self.hold_after_s = hold_after_s
        self.land_after_s = land_after_s
        self.state: VisionLossAction | None = None  # None: vision flowing (or on the ground)
        self._lost_since_s: float | None = None
        #: Seconds without vision when the latest action was taken.
        self.lost_for_s = 0.0

    @property
    def pose_ok(self) -> bool:
        """False while holding or landing for want of vision: the planner's setpoints are not flown."""
        return self.state not in (VisionLossAction.HOLD, VisionLossAction.LAND)

    def step(self, now_s: float, vision_age_s: float | None, in_air: bool) -> VisionLossAction | None:
        """The action to take now (None: nothing changes). ``vision_age_s``: seconds since the
        last vision message went out (None: none yet)."""
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
        if self.lost_for_s >= self.land_after_s:
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

    ``vision_age_s()``: seconds since our last vision message (None: none yet); ``in_air()``:
    the vehicle is flying; ``land()``: stop the mission and land (awaited once)."""

    def __init__(self, monitor: VisionLossMonitor, link: MavlinkLink, vision_age_s: Callable[[], float | None],
                 in_air: Callable[[], bool], land: Callable[[], Awaitable[None]], *,
                 clock: Callable[[], float], period_s: float = GUARD_PERIOD_S) -> None:
        self.monitor = monitor
        self.link = link
        self.vision_age_s = vision_age_s
        self.in_air = in_air
        self.land = land
        self.clock = clock
        self.period_s = period_s
        #: Every action taken, as (clock s, action, seconds without vision).
        self.events: list[tuple[float, VisionLossAction, float]] = []

    async def run(self) -> None:
        while True:
            await self.check()
            await asyncio.sleep(self.period_s)

    async def check(self) -> VisionLossAction | None:
        now = self.clock()
        action = self.monitor.step(now, self.vision_age_s(), self.in_air())
        if action is None:
            return None
        lost = self.monitor.lost_for_s
        self.events.append((now, action, lost))
        if action is VisionLossAction.HOLD:
            log.warning("SLAM pose lost for %.1f s: holding on PX4's estimate, landing after %.1f s without it",
                        lost, self.monitor.land_after_s)
            send_statustext(self.link, mavlink.MAV_SEVERITY_WARNING, f"SLAM lost: holding, land in "
                            f"{max(0.0, self.monitor.land_after_s - lost):.0f}s")
        elif action is VisionLossAction.RESUME:
            log.warning("SLAM pose back: resuming")
            send_statustext(self.link, mavlink.MAV_SEVERITY_NOTICE, "SLAM back: resuming")
        else:
            log.error("SLAM pose lost for %.1f s (limit %.1f s): landing", lost, self.monitor.land_after_s)
            send_statustext(self.link, mavlink.MAV_SEVERITY_CRITICAL, f"SLAM lost {lost:.0f}s: landing")
            try:
                await self.land()
            except CompanionError as exc:
                log.error("SLAM lost and the landing could not be commanded: %s", exc)
        return action

