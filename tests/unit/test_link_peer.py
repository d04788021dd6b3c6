"""The ``udpin`` link is locked to its peer: garbage and strangers never divert what we send.

A raw UDP socket plays the autopilot (system 1, component 1), others the strangers.
"""

from __future__ import annotations

import asyncio
import os
import socket
from collections.abc import Iterator

import pytest
from pymavlink.dialects.v20 import common as mavlink

from companion.mavlink.link import MavlinkLink, first_packet_ids


def _heartbeat(system_id: int = 1, component_id: int = 1, custom_mode: int = 0) -> bytes:
    mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
    return bytes(mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, custom_mode,
                                      mavlink.MAV_STATE_ACTIVE).pack(mav))


@pytest.fixture
def sockets() -> Iterator[list[socket.socket]]:
    socks = []
    for _ in range(3):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        s.setblocking(False)
        socks.append(s)
    yield socks
    for s in socks:
        s.close()


def _received(s: socket.socket) -> int:
    n = 0
    while True:
        try:
            s.recv(4096)
        except BlockingIOError:
            return n
        n += 1


def test_first_packet_ids_reads_whole_packets_only() -> None:
    hb = _heartbeat(7, 9)
    assert first_packet_ids(hb) == (7, 9)
    assert first_packet_ids(hb[:-1]) is None
    assert first_packet_ids(b"\xfd" + bytes(5)) is None
    assert first_packet_ids(os.urandom(3)) is None


@pytest.mark.asyncio
async def test_garbage_and_strangers_never_take_the_peer(sockets: list[socket.socket]) -> None:
    autopilot, stranger, other_system = sockets
    async with MavlinkLink("udpin://127.0.0.1:0", heartbeat_rate_hz=50.0, peer_system=1, peer_component=1,
                           peer_timeout_s=1.0) as link:
        port = link.transport.local_address[1]  # type: ignore[attr-defined]
        addr = ("127.0.0.1", port)
        # Before any peer: garbage and another system's valid packets pick nobody.
        for _ in range(50):
            stranger.sendto(os.urandom(40), addr)
        other_system.sendto(_heartbeat(system_id=42), addr)
        await asyncio.sleep(0.2)
        assert link.stats.peer is None
        # (a random datagram can look like a whole packet from a stranger: counted there)
        assert link.stats.garbage_dropped + link.stats.strangers_dropped >= 51
        assert link.stats.strangers_dropped >= 1
        # The autopilot's first packet picks it.
        heartbeats = link.subscribe("HEARTBEAT")
        autopilot.sendto(_heartbeat(), addr)
        await asyncio.wait_for(heartbeats.get(), 2.0)
        assert link.stats.peer == f"127.0.0.1:{autopilot.getsockname()[1]}"
        # While it is alive, a packet with its ids from another address (a spoofed mode
        # change) is ignored and counted, and garbage changes nothing.
        strangers = link.stats.strangers_dropped
        for _ in range(10):
            autopilot.sendto(_heartbeat(), addr)
            stranger.sendto(_heartbeat(custom_mode=3 << 16), addr)
            stranger.sendto(os.urandom(30), addr)
            await asyncio.sleep(0.02)
        await asyncio.sleep(0.1)
        got = []
        while (m := heartbeats.get_nowait()) is not None:
            got.append(m.custom_mode)
        assert got and set(got) == {0}
        assert link.stats.strangers_dropped >= strangers + 10
        assert link.stats.peer_changes == 1
        # What we send goes to the autopilot only.
        _received(autopilot), _received(stranger)
        await asyncio.sleep(0.2)
        assert _received(autopilot) >= 5 and _received(stranger) == 0


@pytest.mark.asyncio
async def test_the_peer_changes_only_after_it_was_silent_for_the_timeout(sockets: list[socket.socket]) -> None:
    autopilot, successor, _ = sockets
    async with MavlinkLink("udpin://127.0.0.1:0", heartbeat_rate_hz=0.0, peer_system=1, peer_component=1,
                           peer_timeout_s=0.5) as link:
        addr = ("127.0.0.1", link.transport.local_address[1])  # type: ignore[attr-defined]
        autopilot.sendto(_heartbeat(), addr)
        await asyncio.sleep(0.1)
        successor.sendto(_heartbeat(), addr)
        await asyncio.sleep(0.1)
        assert link.stats.peer == f"127.0.0.1:{autopilot.getsockname()[1]}"
        await asyncio.sleep(0.5)  # the autopilot went quiet (e.g. restarted on another port)
        successor.sendto(_heartbeat(), addr)
        await asyncio.sleep(0.1)
        assert link.stats.peer == f"127.0.0.1:{successor.getsockname()[1]}"
        assert link.stats.peer_changes == 2


@pytest.mark.asyncio
async def test_a_garbage_flood_does_not_divert_setpoints(sockets: list[socket.socket]) -> None:
    autopilot, stranger, _ = sockets
    async with MavlinkLink("udpin://127.0.0.1:0", heartbeat_rate_hz=0.0, peer_system=1, peer_component=1) as link:
        addr = ("127.0.0.1", link.transport.local_address[1])  # type: ignore[attr-defined]
        autopilot.sendto(_heartbeat(), addr)
        await asyncio.sleep(0.1)
        _received(autopilot)
        for i in range(2000):
            stranger.sendto(os.urandom(20 + i % 200), addr)
            if i % 100 == 0:
                link.send(link.mav.heartbeat_encode(mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                                                    mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0))
                await asyncio.sleep(0.005)
        await asyncio.sleep(0.2)
        assert _received(autopilot) == 20 and _received(stranger) == 0
        assert link.stats.garbage_dropped > 1000
