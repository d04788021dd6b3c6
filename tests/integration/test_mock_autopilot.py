"""The mock autopilot against a raw pymavlink client on loopback (no MAVSDK).

These pin the protocol behaviour our own link relies on: heartbeat/mode encoding, command acks
and duplicate handling, parameters, the mission protocol, offboard acceptance and failsafe,
and survival of garbage on the socket.
"""

from __future__ import annotations

import asyncio
import math
from typing import Any

import pytest
import pytest_asyncio
from pymavlink.dialects.v20 import common as mavlink
from raw_mavlink_client import RawClient

from companion import px4
from companion.px4 import MAV_PARAM_TYPE_INT32, FlightMode, decode_param_value, encode_param_value
from companion.sim.autopilot import MockAutopilot

pytestmark = [pytest.mark.asyncio, pytest.mark.timeout(60)]

NAN = math.nan


@pytest_asyncio.fixture
async def link():
    client = RawClient()
    # Brisk takeoff/landing keeps the suite short; the behaviour under test is unchanged.
    params = {"MPC_TKO_SPEED": 3.0, "MPC_LAND_SPEED": 1.5}
    async with MockAutopilot(local_port=0, remote_ports=[client.port], params=params) as ap:
        client.ap_addr = ("127.0.0.1", ap.local_port)

        async def keep_reading() -> None:  # like a real client: never let the socket overflow
            while True:
                client._drain()
                await asyncio.sleep(0.01)

        reader = asyncio.create_task(keep_reading())
        await client.wait_ready()  # as a client of real PX4 must before arming
        yield ap, client
        reader.cancel()
    client.close()


async def _fly_to_hold(ap: MockAutopilot, c: RawClient) -> None:
    assert await c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    assert await c.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, NAN, NAN, NAN, NAN) == \
        mavlink.MAV_RESULT_ACCEPTED
    await ap.wait_until(lambda: ap.mode is FlightMode.HOLD and ap.position_ned_m[2] < -2.3,
                        15.0, "takeoff to MIS_TAKEOFF_ALT")


async def test_heartbeat_is_px4_with_custom_mode(link) -> None:
    ap, c = link
    hb = await c.recv("HEARTBEAT")
    assert hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4 and hb.type == mavlink.MAV_TYPE_QUADROTOR
    decoded = px4.decode_heartbeat(hb.base_mode, hb.custom_mode)
    assert decoded.mode is FlightMode.HOLD and not decoded.armed
    for mtype in ("SYS_STATUS", "EXTENDED_SYS_STATE", "ATTITUDE", "LOCAL_POSITION_NED",
                  "GLOBAL_POSITION_INT", "HOME_POSITION", "MISSION_CURRENT"):
        await c.recv(mtype)
    home = await c.recv("HOME_POSITION")
    assert home.latitude == round(ap.home.lat_deg * 1e7)


async def test_arm_takeoff_land_disarms(link) -> None:
    ap, c = link
    ap.params.set("COM_DISARM_LAND", 0.5)
    await _fly_to_hold(ap, c)
    state = await c.recv("EXTENDED_SYS_STATE")
    assert state.landed_state == mavlink.MAV_LANDED_STATE_IN_AIR
    pos = await c.recv("LOCAL_POSITION_NED")
    home = await c.recv("HOME_POSITION", timeout_s=5.0)
    # PX4's local origin is not the floor: the height is relative to home.
    assert pos.z - home.z == pytest.approx(-2.5, abs=0.15)
    # Disarming in the air is refused without the force magic number.
    assert await c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0) == mavlink.MAV_RESULT_DENIED
    assert await c.command(mavlink.MAV_CMD_NAV_LAND) == mavlink.MAV_RESULT_ACCEPTED
    await ap.wait_until(lambda: not ap.armed, 15.0, "land and auto-disarm")
    assert ap.position_ned_m[2] == pytest.approx(0.0, abs=0.02)
    # PX4-style STATUSTEXT reports the events a ground station shows.
    assert c.status_texts() == ["Ready for takeoff!", "Takeoff detected", "Disarming denied: not landed", "Landing detected",
                     "Disarmed by landing"]


async def test_duplicate_command_acked_but_executed_once(link) -> None:
    ap, c = link
    msg = c.mav.command_long_encode(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0,
                                    0, 0, 0)
    c.send(msg)
    c.send(c.mav.command_long_encode(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, 1, 0, 0, 0,
                                     0, 0, 0))
    await asyncio.sleep(0.3)
    c._drain()
    acks = [m for m in c.log if m.get_type() == "COMMAND_ACK"]
    assert [a.result for a in acks] == [mavlink.MAV_RESULT_ACCEPTED] * 2
    records = ap.commands.received(mavlink.MAV_CMD_COMPONENT_ARM_DISARM)
    assert [r.duplicate for r in records] == [False, True]


async def test_rejected_and_ignored_commands(link) -> None:
    ap, c = link
    ap.faults.reject_commands.add(mavlink.MAV_CMD_COMPONENT_ARM_DISARM)
    assert await c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_DENIED
    assert not ap.armed
    ap.faults.reject_commands.clear()
    ap.faults.ignore_commands.add(mavlink.MAV_CMD_NAV_LAND)
    with pytest.raises(AssertionError, match="no COMMAND_ACK"):
        await c.command(mavlink.MAV_CMD_NAV_LAND, timeout_s=0.5)
    assert await c.command(999) == mavlink.MAV_RESULT_UNSUPPORTED
    # Takeoff without arming is refused.
    assert await c.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, NAN, NAN, NAN, NAN) == \
        mavlink.MAV_RESULT_DENIED


async def test_request_message_and_interval(link) -> None:
    ap, c = link
    since = c.mark()
    assert await c.command(mavlink.MAV_CMD_REQUEST_MESSAGE,
                           mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION) == mavlink.MAV_RESULT_ACCEPTED
    ver = await c.recv("AUTOPILOT_VERSION", since=since)
    assert ver.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    assert await c.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                           mavlink.MAVLINK_MSG_ID_BATTERY_STATUS, -1) == mavlink.MAV_RESULT_ACCEPTED
    await asyncio.sleep(0.1)
    before = c.count("BATTERY_STATUS")
    await asyncio.sleep(1.5)
    assert c.count("BATTERY_STATUS") == before
    assert await c.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                           mavlink.MAVLINK_MSG_ID_HEARTBEAT, 100_000) == mavlink.MAV_RESULT_ACCEPTED
    before = c.count("HEARTBEAT")
    await asyncio.sleep(1.0)
    assert c.count("HEARTBEAT") - before >= 5


async def test_params_bytewise_int_and_float(link) -> None:
    ap, c = link
    c.send(c.mav.param_request_read_encode(1, 1, b"MIS_TAKEOFF_ALT", -1))
    pv = await c.recv("PARAM_VALUE", pred=lambda m: m.param_id == "MIS_TAKEOFF_ALT")
    assert pv.param_value == pytest.approx(2.5)
    c.send(c.mav.param_set_encode(1, 1, b"COM_OBL_RC_ACT", encode_param_value(4, MAV_PARAM_TYPE_INT32),
                                  MAV_PARAM_TYPE_INT32))
    pv = await c.recv("PARAM_VALUE", pred=lambda m: m.param_id == "COM_OBL_RC_ACT")
    assert decode_param_value(pv.param_value, pv.param_type) == 4
    assert ap.params.get("COM_OBL_RC_ACT") == 4
    # A set with the wrong type is refused: the answer carries the unchanged value.
    c.send(c.mav.param_set_encode(1, 1, b"MIS_TAKEOFF_ALT", encode_param_value(7, MAV_PARAM_TYPE_INT32),
                                  MAV_PARAM_TYPE_INT32))
    pv = await c.recv("PARAM_VALUE", pred=lambda m: m.param_id == "MIS_TAKEOFF_ALT")
    assert pv.param_value == pytest.approx(2.5) and ap.params.get("MIS_TAKEOFF_ALT") == 2.5
    c.send(c.mav.param_request_list_encode(1, 1))
    await asyncio.sleep(0.5)
    assert c.count("PARAM_VALUE") >= len(ap.params)


async def _upload(c: RawClient, items: list[tuple[float, float, float]], mission_type: int = 0,
                  drop_first: bool = False) -> int:
    c.send(c.mav.mission_count_encode(1, 1, len(items), mission_type))
    dropped = not drop_first
    while True:
        msg = await c.recv("MISSION_REQUEST_INT")
        seq = msg.seq
        if not dropped and seq == 1:
            dropped = True  # pretend this item got lost: the vehicle must re-request it
            continue
        lat, lon, alt = items[seq]
        c.send(c.mav.mission_item_int_encode(
            1, 1, seq, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mavlink.MAV_CMD_NAV_WAYPOINT,
            int(seq == 0), 1, 0, 0.3, 0, NAN, int(round(lat * 1e7)), int(round(lon * 1e7)), alt,
            mission_type))
        if seq == len(items) - 1:
            ack = await c.recv("MISSION_ACK")
            return int(ack.type)


async def test_mission_upload_download_fly(link) -> None:
    ap, c = link
    home = ap.home
    pts = [home.to_global(n, e, 0.0)[:2] + (alt,) for n, e, alt in
           [(2.0, 0.0, 2.0), (2.0, 2.0, 2.5), (0.0, 2.0, 2.0)]]
    assert await _upload(c, pts, drop_first=True) == mavlink.MAV_MISSION_ACCEPTED
    assert len(ap.mission_items()) == 3
    # download
    c.send(c.mav.mission_request_list_encode(1, 1, 0))
    count = await c.recv("MISSION_COUNT")
    assert count.count == 3
    c.send(c.mav.mission_request_int_encode(1, 1, 2, 0))
    item = await c.recv("MISSION_ITEM_INT")
    assert (item.seq, item.x, item.y) == (2, round(pts[2][0] * 1e7), round(pts[2][1] * 1e7))
    c.send(c.mav.mission_ack_encode(1, 1, 0, 0))
    # fly it: arm, MISSION mode takes off first
    assert await c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    assert await c.command(mavlink.MAV_CMD_DO_SET_MODE, *px4.set_mode_params(FlightMode.MISSION)) \
        == mavlink.MAV_RESULT_ACCEPTED
    await ap.wait_until(lambda: ap.navigator.mission_state == mavlink.MISSION_STATE_COMPLETE,
                        30.0, "mission complete")
    assert ap.reached_items == [0, 1, 2]
    n, e, d = ap.position_ned_m
    assert math.hypot(n - 0.0, e - 2.0) < 0.4 and d == pytest.approx(-2.0, abs=0.3)
    cur = await c.recv("MISSION_CURRENT")
    assert cur.seq == 2 and cur.mission_state == mavlink.MISSION_STATE_COMPLETE


async def test_mission_rejected_item_and_clear(link) -> None:
    ap, c = link
    home = ap.home
    pts = [home.to_global(1.0 * i, 0.0, 0.0)[:2] + (2.0,) for i in range(4)]
    ap.faults.reject_mission_seq = 2
    assert await _upload(c, pts[:2]) == mavlink.MAV_MISSION_ACCEPTED
    c.send(c.mav.mission_count_encode(1, 1, 4, 0))
    for _ in range(3):
        req = await c.recv("MISSION_REQUEST_INT")
        lat, lon, alt = pts[req.seq]
        c.send(c.mav.mission_item_int_encode(
            1, 1, req.seq, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mavlink.MAV_CMD_NAV_WAYPOINT,
            0, 1, 0, 0, 0, NAN, int(lat * 1e7), int(lon * 1e7), alt, 0))
        if req.seq == 2:
            break
    ack = await c.recv("MISSION_ACK")
    assert ack.type == mavlink.MAV_MISSION_DENIED
    assert len(ap.mission_items()) == 2  # the previous mission is kept
    c.send(c.mav.mission_clear_all_encode(1, 1, 0))
    ack = await c.recv("MISSION_ACK")
    assert ack.type == mavlink.MAV_MISSION_ACCEPTED and ap.mission_items() == []
    # MISSION mode without a mission is refused
    assert await c.command(mavlink.MAV_CMD_DO_SET_MODE, *px4.set_mode_params(FlightMode.MISSION)) \
        == mavlink.MAV_RESULT_TEMPORARILY_REJECTED


def _position_setpoint(c: RawClient, n: float, e: float, d: float, yaw: float = 0.0) -> Any:
    mask = (mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE
            | mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE
            | mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE
            | mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE)
    return c.mav.set_position_target_local_ned_encode(0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, mask,
                                                      n, e, d, 0, 0, 0, 0, 0, 0, yaw, 0)


async def test_offboard_refused_without_setpoints_then_failsafe_to_hold(link) -> None:
    ap, c = link
    offboard = px4.set_mode_params(FlightMode.OFFBOARD)
    ap.params.set("COM_OBL_RC_ACT", 5)  # Hold on offboard loss (PX4's default: Position mode)
    await _fly_to_hold(ap, c)
    # Flying, Offboard needs the setpoint stream first (disarmed, PX4 accepts any mode).
    assert await c.command(mavlink.MAV_CMD_DO_SET_MODE, *offboard) == \
        mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    home = await c.recv("HOME_POSITION", timeout_s=5.0)  # setpoints 2 m above home

    stop = asyncio.Event()

    async def stream() -> None:
        while not stop.is_set():
            c.send(_position_setpoint(c, 1.0, 1.0, home.z - 2.0, math.pi / 2))
            await asyncio.sleep(0.05)

    task = asyncio.create_task(stream())
    await asyncio.sleep(0.3)
    assert await c.command(mavlink.MAV_CMD_DO_SET_MODE, *offboard) == mavlink.MAV_RESULT_ACCEPTED
    await ap.wait_until(lambda: math.dist(ap.position_ned_m, (1.0, 1.0, -2.0)) < 0.1
                        and abs(ap.vehicle.yaw_rad - math.pi / 2) < 0.05, 15.0,
                        "offboard position and yaw reached")
    stop.set()
    await task
    await ap.wait_until(lambda: ap.mode is FlightMode.HOLD, 5.0, "offboard loss failsafe")
    assert ap.failsafes[-1].reason == "offboard setpoint loss"
    assert ap.in_air  # Hold keeps it flying


async def test_link_drop_and_garbage_survive(link) -> None:
    ap, c = link
    await c.recv("HEARTBEAT")
    ap.faults.drop_link = True
    await asyncio.sleep(0.2)
    c._drain()
    n = len(c.log)
    await asyncio.sleep(1.2)
    c._drain()
    assert len(c.log) == n
    ap.faults.drop_link = False
    await c.recv("HEARTBEAT")
    # Garbage in both directions: the mock keeps answering, and counts what it dropped.
    for i in range(50):
        c.send_raw(bytes([0xFD, 0x09]) + bytes((i * 37 + k) % 256 for k in range(60)))
    c.send_raw(b"\x00" * 300)
    ap.inject_garbage(200)
    assert await c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    assert ap.bad_packets > 0
    ap.faults.corrupt_bytes_rate = 0.01
    await asyncio.sleep(0.5)
    ap.faults.corrupt_bytes_rate = 0.0
    await c.recv("HEARTBEAT")


async def test_vision_messages_recorded(link) -> None:
    ap, c = link
    c.send(c.mav.vision_position_estimate_encode(123456, 1.0, 2.0, -0.5, 0.0, 0.0, 0.3))
    c.send(c.mav.odometry_encode(
        223456, mavlink.MAV_FRAME_LOCAL_FRD, mavlink.MAV_FRAME_BODY_FRD, 1.5, 2.5, -1.0,
        [1, 0, 0, 0], 0, 0, 0, 0, 0, 0, [NAN] * 21, [NAN] * 21))
    await ap.wait_until(lambda: len(ap.vision) == 2, 2.0, "two vision messages")
    assert ap.vision[0].position_ned_m == (1.0, 2.0, -0.5)
    assert ap.vision[1].msg_type == "ODOMETRY" and ap.vision[1].time_usec == 223456


async def test_rtl_returns_home_and_lands(link) -> None:
    ap, c = link
    ap.params.set("COM_DISARM_LAND", 0.3)
    await _fly_to_hold(ap, c)
    # Reposition (COMMAND_INT, as MAVSDK's goto_location sends it) 3 m north-east.
    lat, lon, _ = ap.home.to_global(3.0, 3.0, 0.0)
    since = c.mark()
    c.send(c.mav.command_int_encode(1, 1, mavlink.MAV_FRAME_GLOBAL_INT,
                                    mavlink.MAV_CMD_DO_REPOSITION, 0, 0, -1, 0, 0, NAN,
                                    int(lat * 1e7), int(lon * 1e7), ap.home.alt_m + 2.0))
    ack = await c.recv("COMMAND_ACK", since=since)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED and ap.mode is FlightMode.HOLD
    await ap.wait_until(lambda: math.dist(ap.position_ned_m, (3.0, 3.0, -2.0)) < 0.1, 15.0,
                        "repositioned")
    assert await c.command(mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH) == mavlink.MAV_RESULT_ACCEPTED
    await ap.wait_until(lambda: not ap.armed, 30.0, "RTL, land and disarm")
    n, e, d = ap.position_ned_m
    assert math.hypot(n, e) < 0.35 and d == 0.0


async def test_mission_pause_resume_and_set_current(link) -> None:
    ap, c = link
    pts = [ap.home.to_global(n, 0.0, 0.0)[:2] + (2.0,) for n in (2.0, 4.0, 6.0)]
    assert await _upload(c, pts) == mavlink.MAV_MISSION_ACCEPTED
    # Jump to item 1 before starting (MISSION_SET_CURRENT): the vehicle answers MISSION_CURRENT.
    c.send(c.mav.mission_set_current_encode(1, 1, 1))
    cur = await c.recv("MISSION_CURRENT", pred=lambda m: m.seq == 1)
    assert cur.total == 3
    assert await c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    assert await c.command(mavlink.MAV_CMD_MISSION_START, 0, 0) == mavlink.MAV_RESULT_ACCEPTED
    await ap.wait_until(lambda: ap.reached_items == [1], 20.0, "item 1 reached")
    # Pause (Hold), then resume: it continues with item 2, item 0 is never flown.
    assert await c.command(mavlink.MAV_CMD_DO_SET_MODE, *px4.set_mode_params(FlightMode.HOLD)) \
        == mavlink.MAV_RESULT_ACCEPTED
    assert ap.navigator.mission_state == mavlink.MISSION_STATE_PAUSED
    assert await c.command(mavlink.MAV_CMD_DO_SET_MODE, *px4.set_mode_params(FlightMode.MISSION)) \
        == mavlink.MAV_RESULT_ACCEPTED
    await ap.wait_until(lambda: ap.navigator.mission_state == mavlink.MISSION_STATE_COMPLETE,
                        20.0, "mission complete")
    assert ap.reached_items == [1, 2]
    assert await c.command(mavlink.MAV_CMD_DO_SET_MISSION_CURRENT, 7) == mavlink.MAV_RESULT_DENIED


async def test_fence_and_rally_are_stored_separately(link) -> None:
    ap, c = link
    pts = [ap.home.to_global(n, 1.0, 0.0)[:2] + (2.0,) for n in (1.0, 2.0)]
    assert await _upload(c, pts) == mavlink.MAV_MISSION_ACCEPTED
    assert await _upload(c, pts[:1], mission_type=mavlink.MAV_MISSION_TYPE_RALLY) == \
        mavlink.MAV_MISSION_ACCEPTED
    assert len(ap.mission_items(mavlink.MAV_MISSION_TYPE_RALLY)) == 1
    assert len(ap.mission_items()) == 2
    c.send(c.mav.mission_clear_all_encode(1, 1, mavlink.MAV_MISSION_TYPE_ALL))
    assert (await c.recv("MISSION_ACK")).type == mavlink.MAV_MISSION_ACCEPTED
    assert ap.mission_items() == [] and ap.mission_items(mavlink.MAV_MISSION_TYPE_RALLY) == []


async def test_delayed_link_still_answers(link) -> None:
    ap, c = link
    ap.faults.delay_s = 0.6
    # Shorter than the injected delay: the ack is late ...
    with pytest.raises(AssertionError, match="no COMMAND_ACK"):
        await c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, timeout_s=0.3)
    # ... but it does arrive, and the command was executed exactly once.
    await c.recv("COMMAND_ACK", timeout_s=3.0, since=0,
                 pred=lambda m: m.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM)
    assert ap.armed
    assert len(ap.commands.received(mavlink.MAV_CMD_COMPONENT_ARM_DISARM)) == 1


async def test_truncated_datagram_does_not_swallow_the_next_one(link) -> None:
    """Regression: a stream parser kept the partial packet and ate the next datagram's start."""
    ap, c = link
    whole = c.mav.command_long_encode(1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                      mavlink.MAVLINK_MSG_ID_HOME_POSITION, 0, 0, 0, 0, 0, 0)
    c.send_raw(whole.pack(c.mav)[:20])  # a packet cut short: header says more is coming
    assert await c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED


async def test_home_moves_to_where_the_vehicle_arms(link) -> None:
    ap, c = link
    ap.params.set("COM_DISARM_LAND", 0.3)
    await _fly_to_hold(ap, c)
    lat, lon, _ = ap.home.to_global(2.0, 1.0, 0.0)
    c.send(c.mav.command_int_encode(1, 1, mavlink.MAV_FRAME_GLOBAL_INT,
                                    mavlink.MAV_CMD_DO_REPOSITION, 0, 0, -1, 0, 0, NAN,
                                    int(lat * 1e7), int(lon * 1e7), NAN))
    await ap.wait_until(lambda: math.hypot(ap.position_ned_m[0] - 2.0,
                                           ap.position_ned_m[1] - 1.0) < 0.05, 15.0, "moved")
    assert await c.command(mavlink.MAV_CMD_NAV_LAND) == mavlink.MAV_RESULT_ACCEPTED
    await ap.wait_until(lambda: not ap.armed, 15.0, "landed and disarmed")
    assert ap.home_ned_m == (0.0, 0.0, 0.0)
    since = c.mark()
    assert await c.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    home = await c.recv("HOME_POSITION", since=since)
    assert (home.x, home.y) == pytest.approx((2.0, 1.0), abs=0.05)
    assert (home.latitude, home.longitude) == pytest.approx((lat * 1e7, lon * 1e7), abs=10)
    # The local origin (and so the map frame) does not move with home.
    assert await c.command(mavlink.MAV_CMD_REQUEST_MESSAGE,
                           mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN) == mavlink.MAV_RESULT_ACCEPTED
    origin = await c.recv("GPS_GLOBAL_ORIGIN", since=since)
    assert origin.latitude == round(ap.home.lat_deg * 1e7)
