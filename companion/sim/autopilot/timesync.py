"""The mock autopilot's side of MAVLink time synchronisation, as PX4's ``MavlinkTimesync``.

PX4 asks the other end for its time (TIMESYNC with ``tc1 = 0``, ``ts1`` its own time in ns,
10 Hz on an onboard link), keeps the offset from answers that came back quickly, and once it
has enough converts the companion's timestamps (external vision's ``time_usec``) onto its
clock (``sync_stamp``); before that it uses the arrival time. Requests from the other end are
answered on its own clock.
"""

from __future__ import annotations

from collections import deque

import numpy as np

#: PX4 asks the other end for its time this often (10 Hz on an onboard link) ...
PERIOD_S = 0.1
#: ... and keeps only answers that came back this quickly (``MAX_RTT_SAMPLE``).
MAX_RTT_S = 0.01
#: Samples before the offset is used (PX4: CONVERGENCE_WINDOW, here short for quick tests).
CONVERGED_SAMPLES = 3


class PeerClock:
    """The offset between our clock and the companion's, learned from TIMESYNC answers.
    Times are seconds on our clock (``now``) unless named otherwise."""

    def __init__(self, period_s: float = PERIOD_S, max_rtt_s: float = MAX_RTT_S,
                 converged_samples: int = CONVERGED_SAMPLES) -> None:
        self.period_s = period_s
        self.max_rtt_s = max_rtt_s
        self.converged_samples = converged_samples
        self._offsets: deque[float] = deque(maxlen=15)
        self._next_request_s = 0.0

    def request_due(self, now: float) -> bool:
        """True (once per period) when a request should go out now."""
        if now < self._next_request_s:
            return False
        self._next_request_s = now + self.period_s
        return True

    def add_answer(self, sent_ns: int, remote_ns: int, now: float) -> None:
        """An answer to our request sent at ``sent_ns`` (our clock), stamped ``remote_ns`` by
        the companion; kept when the round trip was short."""
        sent_s, remote_s = sent_ns * 1e-9, remote_ns * 1e-9
        if 0.0 <= now - sent_s < self.max_rtt_s:
            self._offsets.append(0.5 * (sent_s + now) - remote_s)

    @property
    def offset_s(self) -> float | None:
        """Our clock minus the companion's (median of the recent samples; None before any)."""
        return float(np.median(self._offsets)) if self._offsets else None

    def sync_stamp(self, remote_s: float, now: float) -> float:
        """A companion timestamp on our clock once the offset has converged, else ``now``."""
        offset = self.offset_s
        if offset is None or len(self._offsets) < self.converged_samples:
            return now
        return remote_s + offset
