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
