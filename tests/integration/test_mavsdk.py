"""The real MAVSDK library (native 4.x core) against the mock autopilot on loopback.

Three sessions keep the MAVSDK start-up count small: basic flight (telemetry, health, arm,
takeoff, land, rejected command, link loss), missions (upload, download, fly, rejected item,
garbage on the socket), and offboard (position setpoints, setpoint loss -> Hold).
"""

from __future__ import annotations

import asyncio
import math
import socket
from collections.abc import AsyncIterator

import pytest
import pytest_asyncio
from mavsdk.asyncio.plugins.mission import MissionAsync
from mavsdk.plugins.action import ActionError
from mavsdk.plugins.mission import MissionItem as SdkMissionItem
from mavsdk.plugins.mission import MissionPlan as SdkMissionPlan
from mavsdk.plugins.offboard import OffboardError, PositionNedYaw
from mavsdk.plugins.telemetry import FlightMode as SdkFlightMode
from pymavlink.dialects.v20 import common as mavlink

from companion.errors import CommandError, LinkError, MissionError
from companion.mavsdk_client import MavsdkClient
from companion.mission_files import load_mission
from companion.missions import MissionPlan, Waypoint
from companion.px4 import FlightMode
from companion.sim.autopilot import MockAutopilot

pytestmark = [pytest.mark.asyncio, pytest.mark.timeout(120)]

REPO = __import__("pathlib").Path(__file__).resolve().parents[2]


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest_asyncio.fixture
async def session() -> AsyncIterator[tuple[MockAutopilot, MavsdkClient]]:
    port = _free_udp_port()
    # Brisk takeoff/landing keeps the suite short; the behaviour under test is unchanged.
    params = {"MPC_TKO_SPEED": 3.0, "MPC_LAND_SPEED": 1.5, "COM_DISARM_LAND": 0.5}
    async with MockAutopilot(local_port=0, remote_ports=[port], params=params) as ap:
        async with MavsdkClient(f"udpin://127.0.0.1:{port}", connect_timeout_s=10.0) as client:
            yield ap, client


async def _first(gen: AsyncIterator, pred, timeout_s: float = 10.0):  # type: ignore[no-untyped-def]
    """The first item of a MAVSDK subscription matching ``pred`` (closes the subscription)."""
    try:
        async with asyncio.timeout(timeout_s):
            async for item in gen:
                if pred(item):
                    return item
    finally:
        await gen.aclose()  # type: ignore[attr-defined]
    raise AssertionError("subscription ended")


async def _ready(c: MavsdkClient) -> None:
    """Wait, as a client of real PX4 must, until it reports it can arm."""
    await _first(c.telemetry.subscribe_health(), lambda h: h.is_armable, 15.0)


async def test_connect_no_autopilot_is_a_link_error() -> None:
    with pytest.raises(LinkError, match="no autopilot heard"):
        async with MavsdkClient(f"udpin://127.0.0.1:{_free_udp_port()}", connect_timeout_s=0.5):
            pass


async def test_telemetry_health_arm_takeoff_land_and_faults(session) -> None:
    ap, c = session
    tel = c.telemetry
    health = await _first(tel.subscribe_health(),
                          lambda h: h.is_home_position_ok and h.is_global_position_ok and h.is_armable)
    assert health.is_local_position_ok
    home = await c.home()
    assert home.lat_deg == pytest.approx(ap.home.lat_deg, abs=1e-7)
    assert await _first(tel.subscribe_flight_mode(), lambda m: True) == SdkFlightMode.HOLD

    # A rejected command surfaces as MAVSDK's denial, wrapped in our CommandError.
    ap.faults.reject_commands.add(mavlink.MAV_CMD_COMPONENT_ARM_DISARM)
    with pytest.raises(CommandError) as err:
        await c.arm()
    assert err.value.result == "COMMAND_DENIED"
    ap.faults.reject_commands.clear()

    await c.arm()
    assert ap.armed
    await c.action.set_takeoff_altitude(3.0)  # MIS_TAKEOFF_ALT through the param protocol
    assert ap.params.get("MIS_TAKEOFF_ALT") == pytest.approx(3.0)
    await c.action.takeoff()
    pos = await _first(tel.subscribe_position(), lambda p: p.relative_altitude_m > 2.85, 15.0)
    assert pos.latitude_deg == pytest.approx(ap.home.lat_deg, abs=1e-6)
    assert await _first(tel.subscribe_in_air(), lambda v: v)
    await _first(tel.subscribe_flight_mode(), lambda m: m == SdkFlightMode.HOLD, 10.0)

    # Link loss: MAVSDK notices and reconnects when the link comes back; the vehicle holds.
    ap.faults.drop_link = True
    connected = c._system.is_connected_state()  # noqa: SLF001 - MAVSDK's asyncio System
    await _first(connected, lambda v: v is False, 10.0)
    assert ap.mode is FlightMode.HOLD and ap.in_air
    ap.faults.drop_link = False
    await _first(c._system.is_connected_state(), lambda v: v is True, 10.0)  # noqa: SLF001

    await c.action.land()
    assert await _first(tel.subscribe_armed(), lambda a: not a, 20.0) is False
    assert not ap.in_air and ap.position_ned_m[2] == pytest.approx(0.0, abs=0.02)


async def test_mission_upload_download_fly_and_reject(session, tmp_path) -> None:
    ap, c = session
    plan = load_mission(REPO / "config" / "missions" / "square.yaml")
    imap = await c.upload_mission(plan)
    stored = ap.mission_items()
    assert [it.command for it in stored] == [it.command for it in imap.items]
    assert stored[2].x == imap.items[2].x and stored[2].y == imap.items[2].y

    down = await c.download_mission()
    assert [w.action for w in down.waypoints] == [w.action for w in plan.waypoints]
    local = [w.to_local(ap.home) for w in down.waypoints]
    assert local[2].xyz_map_m == pytest.approx((3.0, 3.0, 1.5), abs=0.01)

    # A rejected item names the waypoint; the stored mission is unchanged.
    ap.faults.reject_mission_seq = 4
    with pytest.raises(MissionError, match=r"item 4 of 7 \(waypoint 3, waypoint"):
        await c.upload_mission(plan)
    ap.faults.reject_mission_seq = None
    assert len(ap.mission_items()) == len(stored)

    # Garbage on the socket and corrupted packets while arming and starting: MAVSDK's
    # retries and the mock's duplicate handling get the commands through once each.
    await _ready(c)
    ap.inject_garbage(300)
    ap.faults.corrupt_bytes_rate = 0.002
    await c.arm()
    await c.start_mission()
    await asyncio.sleep(1.0)
    ap.faults.corrupt_bytes_rate = 0.0
    assert ap.mode is FlightMode.MISSION and ap.armed
    await c.wait_mission_finished(timeout_s=60.0)
    assert ap.reached_items[-1] == len(stored) - 1
    assert ap.navigator.mission_state == mavlink.MISSION_STATE_COMPLETE
    # The last item lands: the vehicle ends on the floor at home and disarms.
    await ap.wait_until(lambda: not ap.armed, 15.0, "disarm after the mission's landing")
    n, e, d = ap.position_ned_m
    assert math.hypot(n, e) < 0.5 and d == pytest.approx(0.0, abs=0.02)

    await c.clear_mission()
    assert ap.mission_items() == []
    with pytest.raises(MissionError, match="no items"):
        await c.upload_mission(MissionPlan((), None, "empty"))
    # Local waypoints without a home in the file are placed around the vehicle's home.
    wp = Waypoint(xyz_map_m=(1.0, 2.0, 1.0))
    await c.upload_mission(MissionPlan((wp,), None, "one"))
    it = ap.mission_items()[0]
    n, e, _ = ap.home.to_ned(it.lat_deg, it.lon_deg, ap.home.alt_m)
    assert (e, n) == pytest.approx((1.0, 2.0), abs=0.01)

    # MAVSDK's high-level Mission plugin (what most MAVSDK users call) works against it too.
    mission = MissionAsync(c._system)  # noqa: SLF001 - the connected System
    items = [SdkMissionItem(latitude_deg=lat, longitude_deg=lon, relative_altitude_m=2.0,
                            speed_m_s=1.5, is_fly_through=True)
             for lat, lon, _ in (ap.home.to_global(n, 1.0, 0.0) for n in (1.0, 2.0, 3.0))]
    await mission.upload_mission(SdkMissionPlan(items))
    down_sdk = await mission.download_mission()
    assert [round(i.latitude_deg, 7) for i in down_sdk.mission_items] == \
        [round(i.latitude_deg, 7) for i in items]
    assert all(i.speed_m_s == pytest.approx(1.5) for i in down_sdk.mission_items)


async def test_offboard_position_setpoints_and_setpoint_loss(session) -> None:
    ap, c = session
    ap.params.set("COM_OBL_RC_ACT", 5)  # Hold on offboard loss (PX4's default: Position mode)
    off = c.offboard
    with pytest.raises(OffboardError):
        await off.start()  # no setpoint yet: MAVSDK refuses before asking PX4
    await _ready(c)
    # PX4's local origin is not the floor: setpoint heights are taken from the ground's z.
    ground = await _first(c.telemetry.subscribe_position_velocity_ned(), lambda p: True)
    z0 = ground.position.down_m
    await c.arm()
    await off.set_position_ned(PositionNedYaw(0.0, 0.0, z0 - 1.5, 0.0))
    await off.start()
    assert ap.mode is FlightMode.OFFBOARD
    await off.set_position_ned(PositionNedYaw(2.0, -1.0, z0 - 2.0, 90.0))
    await ap.wait_until(lambda: math.dist(ap.position_ned_m, (2.0, -1.0, -2.0)) < 0.1
                        and abs(ap.vehicle.yaw_rad - math.pi / 2) < 0.05, 20.0,
                        "offboard setpoint reached")
    pos = await _first(c.telemetry.subscribe_position_velocity_ned(),
                       lambda p: abs(p.position.north_m - 2.0) < 0.1)
    assert pos.position.east_m == pytest.approx(-1.0, abs=0.1)
    assert any(s.msg_type == "SET_POSITION_TARGET_LOCAL_NED" for s in ap.setpoints)

    # MAVSDK streams setpoints itself; dropping its packets at the vehicle is a setpoint loss.
    ap.faults.drop_incoming = True
    await ap.wait_until(lambda: ap.mode is FlightMode.HOLD, 5.0, "offboard loss -> Hold")
    ap.faults.drop_incoming = False
    assert ap.failsafes and ap.failsafes[-1].action is FlightMode.HOLD
    assert ap.in_air
    await _first(c.telemetry.subscribe_flight_mode(), lambda m: m == SdkFlightMode.HOLD, 10.0)
    with pytest.raises(ActionError):
        await c.action.disarm()  # in the air: PX4 refuses
