"""Answering the autopilot's TIMESYNC requests (companion.mavlink.timesync)."""

from __future__ import annotations

from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from companion.errors import LinkError
from companion.mavlink.timesync import TimesyncResponder


class _Link:
    def __init__(self) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
        self.sent: list[Any] = []
        self.closed = False

    def send(self, msg: Any) -> None:
        if self.closed:
            raise LinkError("link is not open")
        self.sent.append(msg)


def _from(system: int, tc1: int, ts1: int) -> mavlink.MAVLink_message:
    mav = mavlink.MAVLink(None, srcSystem=system, srcComponent=1)
    return mav.decode(bytearray(mav.timesync_encode(tc1, ts1).pack(mav)))


def test_requests_from_the_autopilot_are_answered_on_our_clock_and_nothing_else() -> None:
    link = _Link()
    ts = TimesyncResponder(link, target_system=1, clock_ns=lambda: 5_000_000_000)  # type: ignore[arg-type]
    ts.handle(_from(1, 0, 123_456_789))
    assert [(m.tc1, m.ts1) for m in link.sent] == [(5_000_000_000, 123_456_789)]
    ts.handle(_from(1, 777, 123_456_789))  # an answer to a request of ours: not a request
    ts.handle(_from(255, 0, 1))  # a ground station's request: not our autopilot
    assert len(link.sent) == 1 and ts.answered == 1
    link.closed = True
    ts.handle(_from(1, 0, 2))  # the link closed under us: no answer, no exception
    assert ts.answered == 1


def test_the_mock_learns_the_offset_from_quick_answers_and_converts_after_three() -> None:
    from companion.sim.autopilot.timesync import PeerClock

    clock = PeerClock(period_s=0.1, max_rtt_s=0.01, converged_samples=3)
    assert clock.request_due(0.0) and not clock.request_due(0.05) and clock.request_due(0.1)
    assert clock.sync_stamp(1000.0, now=5.0) == 5.0  # nothing learned: at arrival
    # Our clock is 995 s behind the companion's; the answers took 2 ms (one took 50 ms).
    clock.add_answer(int(5.000e9), int(1000.001e9), now=5.002)
    clock.add_answer(int(5.100e9), int(1000.101e9), now=5.150)  # too slow: not kept
    clock.add_answer(int(5.200e9), int(1000.201e9), now=5.202)
    assert clock.sync_stamp(1000.0, now=5.3) == 5.3  # two samples: not converged yet
    clock.add_answer(int(5.300e9), int(1000.301e9), now=5.302)
    assert clock.offset_s is not None and abs(clock.offset_s + 995.0) < 1e-6
    assert abs(clock.sync_stamp(1000.4, now=5.45) - 5.4) < 1e-6
