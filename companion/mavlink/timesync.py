"""TIMESYNC both ways: PX4 maps our timestamps onto its clock, we map its clock onto ours.

PX4 sends TIMESYNC with ``tc1 = 0`` and ``ts1`` its time (ns); the other end answers with
``tc1`` its own time (ns) and ``ts1`` echoed. From the answers PX4 estimates the offset
between the clocks (``MavlinkTimesync``) and, once that has converged, converts the
``time_usec`` of our external-vision ODOMETRY into its own time, so EKF2 fuses each pose at
the instant the camera captured it. Without answers it stamps them on arrival (no delay
compensation). Our timestamps are ``time.monotonic`` (the camera's frames and the vision
stream use it), so the answer carries ``time.monotonic_ns()``.

The other way, :class:`AutopilotClock` asks PX4 for its time (``tc1 = 0``, ``ts1`` ours) and
fits our clock against its answers, offset and rate, so telemetry stamped with PX4's
``time_boot_ms`` lands at the right local time even when PX4's clock runs at another rate
(a lockstep simulation runs about 1 % slow; crystals differ by tens of ppm).

PX4 uses our stamps only once its filter has taken ``PX4_TIMESYNC_CONVERGENCE_SAMPLES`` answers;
until then it stamps every pose on arrival, so EKF2 fuses a pose captured a SLAM latency ago
as if it were current and its estimate trails the vehicle by that latency. At PX4's default
TIMESYNC rate on an onboard link (10 Hz) that takes 50 s from the companion's start, longer
than a take-off waits; :class:`TimesyncConvergence` asks PX4 for TIMESYNC at a high rate
until it has answered enough requests, then restores the default rate.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import deque
from collections.abc import Callable

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from companion.errors import CommandError, LinkError
from companion.mavlink.commands import CommandSender
from companion.mavlink.link import MavlinkLink

log = logging.getLogger(__name__)


class TimesyncResponder:
    """Answers TIMESYNC requests from the autopilot (``target_system``) on ``link``; register
    with :meth:`attach`. ``clock_ns``: our clock (``time.monotonic_ns``)."""

    def __init__(self, link: MavlinkLink, target_system: int = 1,
                 clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        self.link = link
        self.target_system = target_system
        self.clock_ns = clock_ns
        self.answered = 0

    def attach(self) -> Callable[[], None]:
        """Listen on the link; returns the function that stops listening."""
        return self.link.add_listener(self.handle, ("TIMESYNC",))

    def handle(self, msg: mavlink.MAVLink_message) -> None:
        if msg.get_srcSystem() != self.target_system or msg.tc1 != 0:
            return  # another system's, or an answer to a request of ours
        try:
            self.link.send(self.link.mav.timesync_encode(self.clock_ns(), int(msg.ts1)))
        except LinkError as exc:
            log.debug("TIMESYNC answer not sent: %s", exc)
            return
        self.answered += 1


class AutopilotClock:
    """Our clock as a function of the autopilot's, from TIMESYNC round trips.

    Every answer gives one sample: the autopilot's time ``tc1`` matched to the midpoint of
    our request and its arrival. Samples whose round trip was slow are dropped (only those
    within ``rtt_margin_s`` of the window's fastest are kept), and a straight line
    ``local = a + b * remote`` is fitted to the rest of the last ``window_s`` seconds, so a
    clock running at another rate is followed, not just offset. :meth:`to_local` is None
    until ``min_samples`` samples span ``min_span_s``."""

    def __init__(self, link: MavlinkLink, target_system: int = 1, *, period_s: float = 0.5,
                 window_s: float = 60.0, rtt_margin_s: float = 0.004, min_samples: int = 5,
                 min_span_s: float = 2.0, clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        self.link = link
        self.target_system = target_system
        self.period_s = period_s
        self.window_s = window_s
        self.rtt_margin_s = rtt_margin_s
        self.min_samples = min_samples
        self.min_span_s = min_span_s
        self.clock_ns = clock_ns
        #: (remote s, local s, round trip s), oldest first.
        self._samples: deque[tuple[float, float, float]] = deque()
        self._fit: tuple[float, float, float] | None = None  # remote reference, local there, rate

    def attach(self) -> Callable[[], None]:
        """Listen for answers on the link; returns the function that stops listening."""
        return self.link.add_listener(self.handle, ("TIMESYNC",))

    async def run(self) -> None:
        """Ask for the autopilot's time every ``period_s`` (a task for the link's lifetime)."""
        while True:
            try:
                self.link.send(self.link.mav.timesync_encode(0, self.clock_ns()))
            except LinkError as exc:
                log.debug("TIMESYNC request not sent: %s", exc)
            await asyncio.sleep(self.period_s)

    def handle(self, msg: mavlink.MAVLink_message) -> None:
        if msg.get_srcSystem() != self.target_system or msg.tc1 == 0:
            return  # another system's, or the autopilot's own request
        self.add_sample(msg.tc1 * 1e-9, msg.ts1 * 1e-9, self.clock_ns() * 1e-9)

    def add_sample(self, remote_s: float, sent_s: float, received_s: float) -> None:
        """One round trip: our request left at ``sent_s``, the answer (autopilot time
        ``remote_s``) arrived at ``received_s``."""
        rtt = received_s - sent_s
        if rtt < 0.0 or rtt > 1.0:
            return  # an answer to a request of a previous run, or one from long ago
        if self._samples and remote_s < self._samples[-1][0] - 1.0:
            self._samples.clear()  # the autopilot rebooted
        self._samples.append((remote_s, 0.5 * (sent_s + received_s), rtt))
        while self._samples and self._samples[-1][0] - self._samples[0][0] > self.window_s:
            self._samples.popleft()
        self._refit()

    def _refit(self) -> None:
        arr = np.array(self._samples)
        keep = arr[arr[:, 2] <= arr[:, 2].min() + self.rtt_margin_s]
        if len(keep) < self.min_samples or keep[-1, 0] - keep[0, 0] < self.min_span_s:
            self._fit = None
            return
        ref = float(keep[-1, 0])
        rate, local_at_ref = np.polyfit(keep[:, 0] - ref, keep[:, 1], 1)
        self._fit = (ref, float(local_at_ref), float(rate))

    @property
    def rate(self) -> float | None:
        """Our seconds per autopilot second (1.0 for clocks at the same rate), or None."""
        return None if self._fit is None else self._fit[2]

    def to_local(self, remote_s: float) -> float | None:
        """Our time of autopilot time ``remote_s``, or None before the fit holds."""
        if self._fit is None:
            return None
        ref, local_at_ref, rate = self._fit
        return local_at_ref + rate * (remote_s - ref)


#: Answers PX4's MavlinkTimesync takes before it maps our stamps (its CONVERGENCE_WINDOW).
PX4_TIMESYNC_CONVERGENCE_SAMPLES = 500


class TimesyncConvergence:
    """Brings PX4's TIMESYNC filter to convergence in seconds: asks for TIMESYNC at
    ``fast_rate_hz`` (``MAV_CMD_SET_MESSAGE_INTERVAL``) until ``margin`` times
    :data:`PX4_TIMESYNC_CONVERGENCE_SAMPLES` requests from the autopilot arrived (each answered
    by the :class:`TimesyncResponder`; the margin covers answers PX4 drops for a slow round
    trip), then asks for its default rate again. :attr:`converged` is our estimate that PX4 now
    maps our stamps; an autopilot that refuses the rate change converges at its own pace."""

    def __init__(self, link: MavlinkLink, commands: CommandSender, target_system: int = 1, *,
                 fast_rate_hz: float = 100.0, samples: int = PX4_TIMESYNC_CONVERGENCE_SAMPLES,
                 margin: float = 1.3) -> None:
        if fast_rate_hz <= 0.0:
            raise ValueError(f"TIMESYNC rate must be > 0 Hz (got {fast_rate_hz})")
        self.link = link
        self.commands = commands
        self.target_system = target_system
        self.fast_rate_hz = fast_rate_hz
        self.needed = int(math.ceil(samples * margin))
        #: Requests from the autopilot seen since :meth:`attach`.
        self.requests = 0
        self._enough = asyncio.Event()

    @property
    def converged(self) -> bool:
        return self.requests >= self.needed

    def attach(self) -> Callable[[], None]:
        """Count the autopilot's requests on the link; returns the function that stops it."""
        return self.link.add_listener(self.handle, ("TIMESYNC",))

    def handle(self, msg: mavlink.MAVLink_message) -> None:
        if msg.get_srcSystem() != self.target_system or msg.tc1 != 0:
            return
        self.requests += 1
        if self.requests >= self.needed:
            self._enough.set()

    async def run(self) -> None:
        """Raise the rate, wait for enough requests, restore the default (one task)."""
        if self.converged:
            return
        t0 = time.monotonic()
        try:
            await self.commands.command_long(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                                             float(mavlink.MAVLINK_MSG_ID_TIMESYNC), 1e6 / self.fast_rate_hz)
        except (CommandError, LinkError) as exc:
            log.info("TIMESYNC at %.0f Hz refused (%s): the autopilot maps our stamps once it has %d answers "
                     "at its own rate", self.fast_rate_hz, exc, self.needed)
            await self._enough.wait()
            return
        await self._enough.wait()
        log.info("TIMESYNC: %d requests answered in %.1f s: the autopilot maps our stamps; back to its default rate",
                 self.requests, time.monotonic() - t0)
        try:
            await self.commands.command_long(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                                             float(mavlink.MAVLINK_MSG_ID_TIMESYNC), 0.0)
        except (CommandError, LinkError) as exc:
            log.warning("TIMESYNC default rate not restored (%s): it stays at %.0f Hz", exc, self.fast_rate_hz)
