"""Answering the autopilot's TIMESYNC requests (companion.mavlink.timesync)."""

from __future__ import annotations

import asyncio
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from companion.errors import LinkError
from companion.mavlink.commands import CommandDeniedError
from companion.mavlink.timesync import (
    PX4_TIMESYNC_CONVERGENCE_SAMPLES,
    TimesyncConvergence,
    TimesyncResponder,
)


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


class _ListeningLink(_Link):
    def __init__(self) -> None:
        super().__init__()
        self.listeners: list[Any] = []

    def add_listener(self, fn: Any, types: Any) -> Any:
        self.listeners.append(fn)
        return lambda: self.listeners.remove(fn)

    def deliver(self, msg: Any) -> None:
        for fn in list(self.listeners):
            fn(msg)


class _Commands:
    def __init__(self, refuse: bool = False) -> None:
        self.calls: list[tuple[int, ...]] = []
        self.refuse = refuse

    async def command_long(self, command: int, *params: float) -> None:
        self.calls.append((command, *params))
        if self.refuse:
            raise CommandDeniedError("MAV_CMD_SET_MESSAGE_INTERVAL was not accepted: DENIED", result="DENIED")


async def _until(cond: Any) -> None:
    for _ in range(200):
        if cond():
            return
        await asyncio.sleep(0.005)
    raise AssertionError("condition not reached")


def test_px4_timesync_is_asked_fast_until_it_has_converged_then_back_to_its_default() -> None:
    asyncio.run(_fast_until_converged())


async def _fast_until_converged() -> None:
    link, cmds = _ListeningLink(), _Commands()
    conv = TimesyncConvergence(link, cmds, target_system=1, fast_rate_hz=100.0, margin=1.2)  # type: ignore[arg-type]
    assert conv.needed == 600 == int(1.2 * PX4_TIMESYNC_CONVERGENCE_SAMPLES)
    conv.attach()
    task = asyncio.create_task(conv.run())
    await _until(lambda: cmds.calls)
    assert cmds.calls == [(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, float(mavlink.MAVLINK_MSG_ID_TIMESYNC), 10_000.0)]
    for k in range(conv.needed - 1):
        link.deliver(_from(1, 0, k + 1))
        link.deliver(_from(1, 5, k + 1))  # answers to our own requests do not count
        link.deliver(_from(255, 0, k + 1))  # nor a ground station's requests
    await asyncio.sleep(0.02)
    assert not conv.converged and len(cmds.calls) == 1 and not task.done()
    link.deliver(_from(1, 0, 10**9))
    await asyncio.wait_for(task, 1.0)
    assert conv.converged
    assert cmds.calls[-1] == (mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, float(mavlink.MAVLINK_MSG_ID_TIMESYNC), 0.0)


def test_an_autopilot_refusing_the_rate_converges_at_its_own_pace() -> None:
    asyncio.run(_refused())


async def _refused() -> None:
    link, cmds = _ListeningLink(), _Commands(refuse=True)
    conv = TimesyncConvergence(link, cmds, target_system=1, samples=3, margin=1.0)  # type: ignore[arg-type]
    conv.attach()
    task = asyncio.create_task(conv.run())
    await _until(lambda: cmds.calls)
    for k in range(3):
        link.deliver(_from(1, 0, k + 1))
    await asyncio.wait_for(task, 1.0)
    assert conv.converged and len(cmds.calls) == 1  # no default rate to restore
