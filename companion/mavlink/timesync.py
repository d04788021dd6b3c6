"""Answering the autopilot's TIMESYNC requests, so PX4 can map our timestamps onto its clock.

PX4 sends TIMESYNC with ``tc1 = 0`` and ``ts1`` its time (ns); the other end answers with
``tc1`` its own time (ns) and ``ts1`` echoed. From the answers PX4 estimates the offset
between the clocks (``MavlinkTimesync``) and, once that has converged, converts the
``time_usec`` of our external-vision ODOMETRY into its own time, so EKF2 fuses each pose at
the instant the camera captured it. Without answers it stamps them on arrival (no delay
compensation). Our timestamps are ``time.monotonic`` (the camera's frames and the vision
stream use it), so the answer carries ``time.monotonic_ns()``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from pymavlink.dialects.v20 import common as mavlink

from companion.errors import LinkError
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
