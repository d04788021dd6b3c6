"""MavlinkLink, commands, state tracking and mission download against a scripted pymavlink peer.

The peer is a bare pymavlink encoder/decoder on a loopback UDP socket, so each test controls
exactly what the "autopilot" says (the full mock autopilot is exercised in
tests/integration/test_link_mock.py).
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import pytest_asyncio
from pymavlink.dialects.v20 import common as mavlink

from companion.errors import CommandError, ConfigError, DataError, LinkError, MissionError
from companion.mavlink.commands import (
    CommandDeniedError,
    CommandSender,
    CommandTimeoutError,
    CommandUnsupportedError,
    VehicleCommands,
)
from companion.mavlink.failsafe import PositionSetpoint
from companion.mavlink.link import MavlinkLink, SigningConfig, load_signing_key
from companion.mavlink.mission_download import download_mission, waypoint_ned_m
from companion.mavlink.obstacle_distance import ObstacleDistanceFeed, ObstacleDistanceInput
from companion.mavlink.offboard import SetpointStreamer
from companion.mavlink.state import HomePosition, LandedState, VehicleStateTracker
from companion.mavlink.tlog import TlogWriter, iter_tlog
from companion.missions import MissionItemInt
from companion.px4 import FlightMode, encode_heartbeat_base_mode
from semmap.costmap import Costmap, VerticalBand
from semmap.grid import GridSpec

Handler = Callable[["Peer", Any], None]


class Peer(asyncio.DatagramProtocol):
    """A scripted autopilot (1/1): decodes what we send, answers through ``handlers``."""

    def __init__(self, signing_key: bytes | None = None) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.mav.robust_parsing = True
        if signing_key is not None:
            self.mav.signing.secret_key = signing_key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.timestamp = 1
        self.received: list[Any] = []
        self.handlers: dict[str, Handler] = {}
        self.transport: asyncio.DatagramTransport | None = None
        self.addr: Any = None

    def datagram_received(self, data: bytes, addr: Any) -> None:
        self.addr = addr
        for msg in self.mav.parse_buffer(data) or []:
            if msg.get_type() == "BAD_DATA":
                continue
            self.received.append(msg)
            handler = self.handlers.get(msg.get_type())
            if handler is not None:
                handler(self, msg)

    def pack(self, msg: Any) -> bytes:
        buf = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        return bytes(buf)

    def send(self, *msgs: Any) -> None:
        """Send messages in ONE datagram."""
        assert self.transport is not None and self.addr is not None
        self.transport.sendto(b"".join(self.pack(m) for m in msgs), self.addr)

    def send_raw(self, data: bytes) -> None:
        assert self.transport is not None and self.addr is not None
        self.transport.sendto(data, self.addr)

    def heartbeat(self, mode: FlightMode = FlightMode.POSCTL, armed: bool = False) -> Any:
        return self.mav.heartbeat_encode(
            mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
            encode_heartbeat_base_mode(mode, armed), mode.custom_mode, mavlink.MAV_STATE_ACTIVE,
        )

    def of_type(self, mtype: str) -> list[Any]:
        return [m for m in self.received if m.get_type() == mtype]


async def _until(cond: Callable[[], bool], timeout_s: float = 3.0) -> None:
    """Poll ``cond`` (the peer's receive callbacks give us nothing to await)."""
    for _ in range(int(timeout_s / 0.01)):
        if cond():
            return
        await asyncio.sleep(0.01)
    raise TimeoutError(f"condition not met within {timeout_s} s")


@pytest_asyncio.fixture
async def peer_and_link() -> AsyncIterator[tuple[Peer, MavlinkLink]]:
    loop = asyncio.get_running_loop()
    async with MavlinkLink("udpin://127.0.0.1:0", heartbeat_rate_hz=20.0) as link:
        port = link.transport.local_address[1]  # type: ignore[attr-defined]
        peer = Peer()
        transport, _ = await loop.create_datagram_endpoint(lambda: peer, remote_addr=("127.0.0.1", port))
        peer.transport = transport
        peer.addr = ("127.0.0.1", port)
        peer.send(peer.heartbeat())  # tells the udpin link where the peer is
        try:
            await _until(lambda: bool(peer.of_type("HEARTBEAT")))
            yield peer, link
        finally:
            transport.close()


@pytest.mark.asyncio
async def test_our_heartbeat_identifies_an_onboard_computer(peer_and_link: tuple[Peer, MavlinkLink]) -> None:
    peer, _ = peer_and_link
    hb = peer.of_type("HEARTBEAT")[0]
    assert hb.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_INVALID
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, mavlink.MAV_COMP_ID_ONBOARD_COMPUTER)
    assert hb.get_header().mlen is not None and hb.get_msgbuf()[0] == mavlink.PROTOCOL_MARKER_V2


@pytest.mark.asyncio
async def test_every_message_of_a_datagram_is_delivered(peer_and_link: tuple[Peer, MavlinkLink]) -> None:
    peer, link = peer_and_link
    async with link.subscribe("ATTITUDE") as sub:
        peer.send(*[peer.mav.attitude_encode(i, 0.1 * i, 0.0, 0.0, 0.0, 0.0, 0.0) for i in range(10)])
        got = [await sub.get(2.0) for _ in range(10)]
    assert [m.time_boot_ms for m in got] == list(range(10))


@pytest.mark.asyncio
async def test_garbage_is_counted_and_the_link_keeps_working(peer_and_link: tuple[Peer, MavlinkLink]) -> None:
    peer, link = peer_and_link
    tracker = VehicleStateTracker()
    tracker.attach(link)
    good = peer.pack(peer.heartbeat(FlightMode.HOLD, armed=True))
    bad_crc = bytearray(peer.pack(peer.heartbeat()))
    bad_crc[-1] ^= 0xFF
    garbage = [
        os.urandom(300),
        b"\xfd\xff" + os.urandom(5),  # a v2 start byte promising 255 bytes, then nothing
        bytes(bad_crc),
        b"\x00" * 7 + good[:9],  # a truncated message
        b"\xfe\x09",  # v1 marker, nothing more
    ]
    for g in garbage:
        peer.send_raw(g)
    peer.send_raw(b"junk" + good)  # garbage then a good message in one datagram
    await tracker.wait_for(lambda s: s.flight_mode is FlightMode.HOLD, 3.0, "HOLD")
    assert link.stats.bad_data >= len(garbage)
    assert tracker.snapshot().armed


@pytest.mark.asyncio
async def test_slow_subscriber_drops_oldest(peer_and_link: tuple[Peer, MavlinkLink]) -> None:
    peer, link = peer_and_link
    sub = link.subscribe("ATTITUDE", maxsize=3)
    peer.send(*[peer.mav.attitude_encode(i, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0) for i in range(8)])
    await _until(lambda: sub.dropped == 5)
    assert [(await sub.get(1.0)).time_boot_ms for _ in range(3)] == [5, 6, 7]
    assert link.stats.queue_dropped >= 5
    sub.close()
    peer.send(peer.mav.attitude_encode(99, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    await asyncio.sleep(0.05)
    assert sub.get_nowait() is None  # closed: no longer fed


@pytest.mark.asyncio
async def test_state_tracker_names_modes_and_reads_telemetry(peer_and_link: tuple[Peer, MavlinkLink]) -> None:
    peer, link = peer_and_link
    tracker = VehicleStateTracker()
    tracker.attach(link)
    m = peer.mav
    peer.send(
        peer.heartbeat(FlightMode.MISSION, armed=True),
        m.local_position_ned_encode(1000, 1.0, 2.0, -3.0, 0.1, 0.2, -0.3),
        m.attitude_encode(1000, 0.01, 0.02, 1.5, 0.0, 0.0, 0.0),
        m.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_UNDEFINED, mavlink.MAV_LANDED_STATE_IN_AIR),
        m.sys_status_encode(0, 0, 0, 500, 15800, -1, 76, 0, 0, 0, 0, 0, 0),
        m.home_position_encode(473977420, 85455940, 488000, 0.5, -0.5, 0.0, [1, 0, 0, 0], 0, 0, 0),
    )
    # A ground station's heartbeat (another component) must not count as the autopilot's.
    gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    peer.send_raw(bytes(gcs.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0).pack(gcs)))
    s = await tracker.wait_for(lambda s: s.home is not None and s.battery_v is not None, 3.0, "telemetry")
    assert s.flight_mode is FlightMode.MISSION and s.armed
    assert s.position_ned_m == pytest.approx((1.0, 2.0, -3.0))
    assert s.velocity_ned_m_s == pytest.approx((0.1, 0.2, -0.3))
    assert s.position_boot_s == pytest.approx(1.0)  # the autopilot's time of the estimate
    assert s.attitude_rpy_rad == pytest.approx((0.01, 0.02, 1.5))
    assert s.yaw_ned_rad == pytest.approx(1.5)
    assert s.landed_state is LandedState.IN_AIR and s.in_air
    assert s.battery_v == pytest.approx(15.8) and s.battery_remaining == pytest.approx(0.76)
    assert s.home == HomePosition(47.397742, 8.545594, 488.0, (0.5, -0.5, 0.0))
    assert s.heartbeat_age_s is not None and s.heartbeat_fresh(1.0)


# --- commands ----------------------------------------------------------------------------

def _answer(results: list[int | None]) -> Handler:
    """COMMAND_LONG handler answering with results in turn (None = stay silent)."""

    def handler(peer: Peer, msg: Any) -> None:
        result = results.pop(0) if results else mavlink.MAV_RESULT_ACCEPTED
        if result is not None:
            peer.send(peer.mav.command_ack_encode(msg.command, result, 0, 0, msg.get_srcSystem(),
                                                  msg.get_srcComponent()))

    return handler


@pytest.mark.asyncio
async def test_command_accepted_and_named_helpers(peer_and_link: tuple[Peer, MavlinkLink]) -> None:
    peer, link = peer_and_link
    peer.handlers["COMMAND_LONG"] = _answer([])
    cmds = VehicleCommands(CommandSender(link, timeout_s=0.5, retries=1))
    await cmds.arm()
    await cmds.set_mode(FlightMode.OFFBOARD)
    await cmds.hold()
    await cmds.land()
    await cmds.return_to_launch()
    await cmds.disarm(force=True)
    await cmds.request_message(mavlink.MAVLINK_MSG_ID_HOME_POSITION)
    await cmds.set_message_interval(mavlink.MAVLINK_MSG_ID_ATTITUDE, 50.0)
    await cmds.set_message_interval(mavlink.MAVLINK_MSG_ID_ATTITUDE, 0.0)
    sent = peer.of_type("COMMAND_LONG")
    assert (sent[6].command, sent[6].param1) == (mavlink.MAV_CMD_REQUEST_MESSAGE, 242.0)
    assert (sent[7].param1, sent[7].param2) == (30.0, 20000.0)
    assert sent[8].param2 == -1.0
    sent = sent[:6]
    assert [m.command for m in sent] == [
        mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_CMD_DO_SET_MODE,
        mavlink.MAV_CMD_NAV_LAND, mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH, mavlink.MAV_CMD_COMPONENT_ARM_DISARM,
    ]
    assert sent[0].param1 == 1.0
    assert (sent[1].param1, sent[1].param2, sent[1].param3) == (1.0, 6.0, 0.0)  # custom, OFFBOARD
    assert (sent[2].param2, sent[2].param3) == (4.0, 3.0)  # AUTO.LOITER
    assert (sent[5].param1, sent[5].param2) == (0.0, 21196.0)


@pytest.mark.asyncio
async def test_takeoff_altitude_is_amsl_from_home(peer_and_link: tuple[Peer, MavlinkLink]) -> None:
    peer, link = peer_and_link
    peer.handlers["COMMAND_LONG"] = _answer([])
    tracker = VehicleStateTracker()
    tracker.attach(link)
    peer.send(peer.mav.home_position_encode(0, 0, 100000, 0.0, 0.0, 0.0, [1, 0, 0, 0], 0, 0, 0))
    await tracker.wait_for(lambda s: s.home is not None, 2.0, "home")
    await VehicleCommands(CommandSender(link), tracker).takeoff(2.5)
    assert peer.of_type("COMMAND_LONG")[-1].param7 == pytest.approx(102.5)


@pytest.mark.parametrize(
    ("result", "error", "name"),
    [
        (mavlink.MAV_RESULT_DENIED, CommandDeniedError, "DENIED"),
        (mavlink.MAV_RESULT_UNSUPPORTED, CommandUnsupportedError, "UNSUPPORTED"),
        (mavlink.MAV_RESULT_FAILED, CommandError, "FAILED"),
    ],
)
@pytest.mark.asyncio
async def test_rejections_become_named_errors(
    peer_and_link: tuple[Peer, MavlinkLink], result: int, error: type[CommandError], name: str
) -> None:
    peer, link = peer_and_link
    peer.handlers["COMMAND_LONG"] = _answer([result])
    with pytest.raises(error) as info:
        await VehicleCommands(CommandSender(link, timeout_s=0.5)).arm()
    assert info.value.result == name
    assert "MAV_CMD_COMPONENT_ARM_DISARM" in str(info.value)
    assert len(peer.of_type("COMMAND_LONG")) == 1  # a rejection is final: no retry


@pytest.mark.asyncio
async def test_lost_commands_are_retried_with_confirmation(peer_and_link: tuple[Peer, MavlinkLink]) -> None:
    peer, link = peer_and_link
    peer.handlers["COMMAND_LONG"] = _answer([None, None, mavlink.MAV_RESULT_ACCEPTED])
    await CommandSender(link, timeout_s=0.2, retries=3).command_long(mavlink.MAV_CMD_NAV_LAND)
    assert [m.confirmation for m in peer.of_type("COMMAND_LONG")] == [0, 1, 2]


@pytest.mark.asyncio
async def test_silence_ends_in_timeout_error(peer_and_link: tuple[Peer, MavlinkLink]) -> None:
    peer, link = peer_and_link
    peer.handlers["COMMAND_LONG"] = _answer([None] * 10)
    with pytest.raises(CommandTimeoutError) as info:
        await CommandSender(link, timeout_s=0.1, retries=2).command_long(mavlink.MAV_CMD_NAV_LAND)
    assert info.value.result == "TIMEOUT"
    assert len(peer.of_type("COMMAND_LONG")) == 3


@pytest.mark.asyncio
async def test_in_progress_waits_without_resending(peer_and_link: tuple[Peer, MavlinkLink]) -> None:
    peer, link = peer_and_link

    def slow(p: Peer, msg: Any) -> None:
        p.send(p.mav.command_ack_encode(msg.command, mavlink.MAV_RESULT_IN_PROGRESS, 10, 0, 1, 191))

        async def later() -> None:
            await asyncio.sleep(0.4)
            p.send(p.mav.command_ack_encode(msg.command, mavlink.MAV_RESULT_ACCEPTED, 100, 0, 1, 191))

        asyncio.get_running_loop().create_task(later())

    peer.handlers["COMMAND_LONG"] = slow
    await CommandSender(link, timeout_s=0.15, retries=0).command_long(mavlink.MAV_CMD_NAV_TAKEOFF)
    assert len(peer.of_type("COMMAND_LONG")) == 1


@pytest.mark.asyncio
async def test_acks_for_other_commands_or_targets_are_ignored(peer_and_link: tuple[Peer, MavlinkLink]) -> None:
    peer, link = peer_and_link

    def confusing(p: Peer, msg: Any) -> None:
        p.send(
            p.mav.command_ack_encode(mavlink.MAV_CMD_NAV_LAND, mavlink.MAV_RESULT_DENIED, 0, 0, 1, 191),
            p.mav.command_ack_encode(msg.command, mavlink.MAV_RESULT_DENIED, 0, 0, 7, 191),  # not us
            p.mav.command_ack_encode(msg.command, mavlink.MAV_RESULT_ACCEPTED, 0, 0, 1, 191),
        )

    peer.handlers["COMMAND_LONG"] = confusing
    await CommandSender(link, timeout_s=0.5, retries=0).command_long(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)


# --- mission download --------------------------------------------------------------------

def _mission_server(items: list[Any], drop_first_request_of: int | None = None) -> dict[str, Handler]:
    dropped: set[int] = set()

    def on_list(p: Peer, msg: Any) -> None:
        p.send(p.mav.mission_count_encode(msg.get_srcSystem(), msg.get_srcComponent(), len(items),
                                          msg.mission_type))

    def on_request(p: Peer, msg: Any) -> None:
        if msg.seq == drop_first_request_of and msg.seq not in dropped:
            dropped.add(msg.seq)
            return
        p.send(items[msg.seq])

    return {"MISSION_REQUEST_LIST": on_list, "MISSION_REQUEST_INT": on_request}


def _item(p: Peer, seq: int, cmd: int, lat: float, lon: float, alt: float,
          frame: int = mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT) -> Any:
    return p.mav.mission_item_int_encode(1, 191, seq, frame, cmd, int(seq == 0), 1, 0.0, 0.5, 0.0,
                                         float("nan"), int(lat * 1e7), int(lon * 1e7), alt)


@pytest.mark.asyncio
async def test_mission_download(peer_and_link: tuple[Peer, MavlinkLink]) -> None:
    peer, link = peer_and_link
    wps = [(47.3977, 8.5456, 2.0), (47.39775, 8.5456, 2.0), (47.39775, 8.54567, 1.5)]
    items = [_item(peer, i, mavlink.MAV_CMD_NAV_WAYPOINT, *wp) for i, wp in enumerate(wps)]
    peer.handlers.update(_mission_server(items, drop_first_request_of=1))
    got = await download_mission(link, timeout_s=0.3)
    assert [i.seq for i in got] == [0, 1, 2]
    assert all(isinstance(i, MissionItemInt) and i.is_navigation for i in got)
    assert got[1].lat_deg == pytest.approx(47.39775) and got[2].lon_deg == pytest.approx(8.54567)
    assert got[0].command_name == "MAV_CMD_NAV_WAYPOINT" and got[0].current
    await _until(lambda: bool(peer.of_type("MISSION_ACK")))
    assert peer.of_type("MISSION_ACK")[-1].type == mavlink.MAV_MISSION_ACCEPTED
    assert [m.seq for m in peer.of_type("MISSION_REQUEST_INT")] == [0, 1, 1, 2]  # one resend
    home = HomePosition(47.3977, 8.5456, 488.0, (0.0, 0.0, 0.0))
    n, e, d = waypoint_ned_m(got[1], home)
    assert n == pytest.approx(5.57, abs=0.05) and e == pytest.approx(0.0, abs=1e-6) and d == pytest.approx(-2.0)
    n, e, _ = waypoint_ned_m(got[2], home)
    assert e == pytest.approx(0.07e-3 * 111319.5 * 0.6769, abs=0.1)


@pytest.mark.asyncio
async def test_empty_mission_and_autopilot_errors(peer_and_link: tuple[Peer, MavlinkLink]) -> None:
    peer, link = peer_and_link
    peer.handlers.update(_mission_server([]))
    assert await download_mission(link, timeout_s=0.3) == ()

    def refuse(p: Peer, msg: Any) -> None:
        p.send(p.mav.mission_ack_encode(1, 191, mavlink.MAV_MISSION_INVALID_SEQUENCE, 0))

    items = [_item(peer, 0, mavlink.MAV_CMD_NAV_WAYPOINT, 47.0, 8.0, 2.0)] * 2
    peer.handlers.update(_mission_server(items))
    peer.handlers["MISSION_REQUEST_INT"] = refuse
    with pytest.raises(MissionError, match="item 0.*MAV_MISSION_INVALID_SEQUENCE"):
        await download_mission(link, timeout_s=0.3)


@pytest.mark.asyncio
async def test_mission_download_gives_up_on_silence(peer_and_link: tuple[Peer, MavlinkLink]) -> None:
    _, link = peer_and_link
    with pytest.raises(MissionError, match="no answer for the item count"):
        await download_mission(link, timeout_s=0.05, retries=1)


def test_waypoint_frames() -> None:
    home = HomePosition(47.0, 8.0, 500.0, (1.0, 2.0, 0.0))
    local = MissionItemInt(0, mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_CMD_NAV_WAYPOINT, 0, 1,
                           0, 0, 0, 0, 30_000, 40_000, -1.0)  # x/y: metres times 1e4
    assert waypoint_ned_m(local, home) == (3.0, 4.0, -1.0)
    amsl = MissionItemInt(0, mavlink.MAV_FRAME_GLOBAL_INT, mavlink.MAV_CMD_NAV_WAYPOINT, 0, 1,
                          0, 0, 0, 0, 470_000_000, 80_000_000, 503.0)
    assert waypoint_ned_m(amsl, home) == pytest.approx((1.0, 2.0, -3.0))
    terrain = MissionItemInt(4, mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT, mavlink.MAV_CMD_NAV_WAYPOINT,
                             0, 1, 0, 0, 0, 0, 470_000_000, 80_000_000, 3.0)
    with pytest.raises(MissionError, match="mission item 4"):
        waypoint_ned_m(terrain, home)


# --- signing -----------------------------------------------------------------------------

@pytest.mark.asyncio
async def test_signed_links_talk_and_reject_strangers(tmp_path: Path) -> None:
    key = bytes(range(32))
    key_file = tmp_path / "mavlink.key"
    key_file.write_text(key.hex() + "\n")
    key_file.chmod(0o600)
    assert load_signing_key(key_file) == key
    signing = SigningConfig(key=load_signing_key(key_file))
    async with MavlinkLink("udpin://127.0.0.1:0", heartbeat_rate_hz=20.0, signing=signing,
                           peer_timeout_s=0.2) as a:
        port = a.transport.local_address[1]  # type: ignore[attr-defined]
        url = f"udpout://127.0.0.1:{port}"
        async with MavlinkLink(url, system_id=1, component_id=1, heartbeat_rate_hz=20.0, signing=signing) as b:
            hb = await a.wait_message("HEARTBEAT", 2.0)
            assert hb.get_signed() and hb.get_srcComponent() == 1
            await b.wait_message("HEARTBEAT", 2.0)
        peer = a.stats.peer
        await asyncio.sleep(0.3)  # the peer is silent: strangers get their signatures checked
        wrong = SigningConfig(key=b"\x01" * 32)
        async with MavlinkLink(url, system_id=1, component_id=2, heartbeat_rate_hz=20.0, signing=wrong), \
                MavlinkLink(url, system_id=1, component_id=3, heartbeat_rate_hz=20.0):
            with pytest.raises(TimeoutError):
                await a.wait_message("HEARTBEAT", 0.5, lambda m: m.get_srcComponent() in (2, 3))
        assert a.stats.signature_rejected > 0
        assert a.stats.peer == peer  # badly signed and unsigned packets never pick the peer


def test_bad_signing_keys_name_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "short.key"
    bad.write_bytes(b"abc")
    bad.chmod(0o600)
    with pytest.raises(ConfigError, match="short.key"):
        load_signing_key(bad)
    with pytest.raises(ConfigError, match="cannot read"):
        load_signing_key(tmp_path / "missing.key")
    with pytest.raises(ConfigError, match="32 bytes"):
        SigningConfig(key=b"x")


# --- other transports --------------------------------------------------------------------

@pytest.mark.asyncio
async def test_tcp_client_and_server_transports() -> None:
    async with MavlinkLink("tcpin://127.0.0.1:0", heartbeat_rate_hz=20.0) as server:
        port = server.transport.local_address[1]  # type: ignore[attr-defined]
        async with MavlinkLink(f"tcp://127.0.0.1:{port}", component_id=1, heartbeat_rate_hz=20.0) as client:
            hb = await server.wait_message("HEARTBEAT", 3.0, lambda m: m.get_srcComponent() == 1)
            assert hb.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
            await client.wait_message("HEARTBEAT", 3.0)


@pytest.mark.asyncio
async def test_serial_transport_over_a_pty() -> None:
    master, slave = os.openpty()
    try:
        os.set_blocking(master, False)
        peer = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        async with MavlinkLink(f"serial://{os.ttyname(slave)}:115200", heartbeat_rate_hz=20.0) as link:
            os.write(master, bytes(peer.heartbeat_encode(
                mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 0).pack(peer)))
            hb = await link.wait_message("HEARTBEAT", 3.0)
            assert hb.get_srcComponent() == 1
            got: list[Any] = []

            async def read_ours() -> None:
                while not got:
                    try:
                        got.extend(m for m in peer.parse_buffer(os.read(master, 1024)) or []
                                   if m.get_type() == "HEARTBEAT")
                    except BlockingIOError:
                        await asyncio.sleep(0.02)

            async with asyncio.timeout(3.0):
                await read_ours()
            assert got[0].type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.asyncio
async def test_open_errors_are_link_errors() -> None:
    with pytest.raises(LinkError, match="serial:///dev/does-not-exist"):
        async with MavlinkLink("serial:///dev/does-not-exist:57600"):
            pass
    async with MavlinkLink("udpin://127.0.0.1:0") as a:
        port = a.transport.local_address[1]  # type: ignore[attr-defined]
        with pytest.raises(LinkError, match="cannot open"):
            async with MavlinkLink(f"udpin://127.0.0.1:{port}"):
                pass
    closed = MavlinkLink("udpout://127.0.0.1:9")
    with pytest.raises(LinkError, match="not open"):
        closed.send(closed.mav.heartbeat_encode(0, 0, 0, 0, 0))


# --- setpoint streaming ------------------------------------------------------------------

@pytest.mark.asyncio
async def test_setpoint_streamer_sends_the_slot_at_a_fixed_rate(peer_and_link: tuple[Peer, MavlinkLink]) -> None:
    peer, link = peer_and_link
    slot: list[PositionSetpoint | None] = [None]
    async with SetpointStreamer(link, 50.0, lambda: slot[0]) as streamer:
        await asyncio.sleep(0.1)
        assert streamer.stats.sent == 0 and streamer.stats.ticks >= 2  # nothing to send yet
        slot[0] = PositionSetpoint((1.0, 2.0, -3.0), yaw_rad=0.5, velocity_ned_m_s=(0.1, 0.0, 0.0))
        await _until(lambda: len(peer.of_type("SET_POSITION_TARGET_LOCAL_NED")) >= 5)
        slot[0] = PositionSetpoint((4.0, 5.0, -6.0))
        await _until(lambda: peer.of_type("SET_POSITION_TARGET_LOCAL_NED")[-1].x == 4.0)
    msgs = peer.of_type("SET_POSITION_TARGET_LOCAL_NED")
    first, last = msgs[0], msgs[-1]
    assert first.coordinate_frame == mavlink.MAV_FRAME_LOCAL_NED
    assert (first.target_system, first.target_component) == (1, 1)
    assert (first.x, first.y, first.z, first.vx) == pytest.approx((1.0, 2.0, -3.0, 0.1))
    assert first.yaw == pytest.approx(0.5)
    accel_yawrate = (mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE
                     | mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE)
    velocity = (mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE
                | mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE)
    assert first.type_mask == accel_yawrate
    assert last.type_mask == accel_yawrate | velocity | mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE
    n = len(msgs)
    await asyncio.sleep(0.1)
    assert len(peer.of_type("SET_POSITION_TARGET_LOCAL_NED")) == n  # the task ended with the context


@pytest.mark.asyncio
async def test_a_failing_setpoint_source_does_not_kill_the_task(peer_and_link: tuple[Peer, MavlinkLink]) -> None:
    peer, link = peer_and_link
    calls = [0]

    def flaky() -> PositionSetpoint:
        calls[0] += 1
        if calls[0] % 2:
            raise RuntimeError("planner bug")
        return PositionSetpoint((0.0, 0.0, -1.0))

    async with SetpointStreamer(link, 50.0, flaky) as streamer:
        await _until(lambda: streamer.stats.sent >= 3)
    assert streamer.stats.ticks >= 6


@pytest.mark.asyncio
async def test_errors_in_the_body_propagate_unwrapped() -> None:
    """Our context managers own task groups; a caller's exception must not become an ExceptionGroup."""
    with pytest.raises(KeyError):
        async with MavlinkLink("udpin://127.0.0.1:0", heartbeat_rate_hz=50.0) as link:
            await asyncio.sleep(0.05)
            raise KeyError("body")
    assert not link.is_open
    async with MavlinkLink("udpin://127.0.0.1:0") as link:
        with pytest.raises(KeyError):
            async with SetpointStreamer(link, 50.0, lambda: None):
                raise KeyError("body")


@pytest.mark.asyncio
async def test_tcp_client_reconnects_when_the_server_comes_back() -> None:
    async with MavlinkLink("tcpin://127.0.0.1:0", heartbeat_rate_hz=20.0) as server:
        port = server.transport.local_address[1]  # type: ignore[attr-defined]
        client = MavlinkLink(f"tcp://127.0.0.1:{port}", component_id=1, heartbeat_rate_hz=20.0)
        async with client:
            await server.wait_message("HEARTBEAT", 3.0, lambda m: m.get_srcComponent() == 1)
            await server.__aexit__(None, None, None)  # the server goes away ...
            await _until(lambda: not client.transport.connected)
            async with MavlinkLink(f"tcpin://127.0.0.1:{port}", heartbeat_rate_hz=20.0) as server2:
                # ... and comes back on the same port: the client finds it again by itself.
                await server2.wait_message("HEARTBEAT", 5.0, lambda m: m.get_srcComponent() == 1)
                await client.wait_message("HEARTBEAT", 3.0)


def test_link_from_config_reads_the_signing_key(tmp_path: Path) -> None:
    from companion.config import LinkConfig

    key_file = tmp_path / "link.key"
    key_file.write_bytes(bytes(range(100, 132)))
    key_file.chmod(0o600)
    link = MavlinkLink.from_config(LinkConfig(url="udpout://127.0.0.1:14580", component_id=191,
                                              signing_key_path=str(key_file)))
    assert link.signing is not None and link.signing.key == bytes(range(100, 132))
    assert link.mav.signing.sign_outgoing
    assert (link.system_id, link.component_id) == (1, 191)
    assert MavlinkLink.from_config(LinkConfig()).signing is None  # off by default
    with pytest.raises(ConfigError, match="missing.key"):
        MavlinkLink.from_config(LinkConfig(signing_key_path=str(tmp_path / "missing.key")))


# --- telemetry logs ----------------------------------------------------------------------

def test_tlog_round_trip_and_damaged_files(tmp_path: Path) -> None:
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    packets = [bytes(mav.attitude_encode(i, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0).pack(mav)) for i in range(3)]
    v1 = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    packets.append(bytes(v1.heartbeat_encode(2, 12, 0, 0, 0).pack(v1, force_mavlink1=True)))
    path = tmp_path / "a.tlog"
    with TlogWriter(path) as w:
        for i, p in enumerate(packets):
            w.write(p, stamp_s=1000.0 + i * 0.1)
    records = list(iter_tlog(path))
    assert [r.packet for r in records] == packets
    assert [r.stamp_s for r in records] == pytest.approx([1000.0, 1000.1, 1000.2, 1000.3])
    # A log cut off mid-packet (power loss) yields the complete records only.
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(path.read_bytes()[:-5])
    assert len(list(iter_tlog(cut))) == 3
    junk = tmp_path / "junk.tlog"
    junk.write_bytes(b"\x00" * 8 + b"not mavlink at all")
    with pytest.raises(DataError, match=r"junk.tlog: not a MAVLink telemetry log \(no packet start at byte 8\)"):
        list(iter_tlog(junk))
    with pytest.raises(DataError, match="cannot read"):
        list(iter_tlog(tmp_path / "missing.tlog"))


@pytest.mark.asyncio
async def test_replay_of_a_missing_log_is_a_link_error(tmp_path: Path) -> None:
    with pytest.raises(LinkError, match="no such telemetry log"):
        async with MavlinkLink(f"tlog://{tmp_path}/missing.tlog"):
            pass


@pytest.mark.asyncio
async def test_closing_the_link_wakes_subscribers() -> None:
    async with MavlinkLink("udpin://127.0.0.1:0") as link:
        waiting = link.subscribe("HEARTBEAT")
        iterating = link.subscribe("ATTITUDE")

        async def consume() -> int:
            return len([m async for m in iterating])

        getter = asyncio.create_task(waiting.get())
        consumer = asyncio.create_task(consume())
        await asyncio.sleep(0.05)
    with pytest.raises(LinkError, match="link closed"):
        await asyncio.wait_for(getter, 2.0)
    assert await asyncio.wait_for(consumer, 2.0) == 0
    assert waiting.get_nowait() is None


@pytest.mark.asyncio
async def test_obstacle_feed_survives_a_failing_source(peer_and_link: tuple[Peer, MavlinkLink]) -> None:
    peer, link = peer_and_link
    spec = GridSpec(0.1, (-10.0, -10.0), (200, 200))
    good = ObstacleDistanceInput(Costmap(spec, np.zeros(spec.shape_rc, np.uint8), VerticalBand(0.0, 1.0)),
                                 (0.0, 0.0), 0.0)
    calls = [0]

    def flaky() -> ObstacleDistanceInput | None:
        calls[0] += 1
        if calls[0] % 2:
            raise RuntimeError("map being rebuilt")
        return good

    async with ObstacleDistanceFeed(link, flaky, rate_hz=50.0) as feed:
        await _until(lambda: len(peer.of_type("OBSTACLE_DISTANCE")) >= 3)
    assert feed.errors >= 2 and feed.sent >= 3
    assert list(peer.of_type("OBSTACLE_DISTANCE")[-1].distances) == [801] * 72
