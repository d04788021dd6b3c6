"""Our own MAVLink link against the mock PX4 autopilot on loopback.

Flies the whole path the service uses: telemetry, arm, takeoff, offboard position setpoints,
mission download and leg-by-leg flight, land; then the faults: link loss, setpoint loss, a
pilot taking over, stale pose, rejected and unanswered commands, garbage on the socket.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import pytest_asyncio
from pymavlink.dialects.v20 import common as mavlink

from companion.config import LinkConfig
from companion.mavlink.commands import (
    CommandDeniedError,
    CommandSender,
    CommandTimeoutError,
    VehicleCommands,
)
from companion.mavlink.failsafe import OffboardState, PositionSetpoint
from companion.mavlink.link import MavlinkLink
from companion.mavlink.mission_download import download_mission, waypoint_ned_m
from companion.mavlink.obstacle_distance import (
    ObstacleDistanceFeed,
    ObstacleDistanceInput,
    compute_obstacle_distances,
)
from companion.mavlink.offboard import OffboardController
from companion.mavlink.state import LandedState, VehicleState, VehicleStateTracker
from companion.mavlink.tlog import iter_tlog
from companion.mavlink.vehicle import Vehicle
from companion.mavlink.vision import vision_odometry_message
from companion.px4 import FlightMode
from companion.sim.autopilot import MockAutopilot
from semmap.costmap import LETHAL_OBSTACLE, Costmap, VerticalBand
from semmap.grid import GridSpec

pytestmark = pytest.mark.timeout(120)

TAKEOFF_ALT_M = 1.5
HB_TIMEOUT_S = 2.0  # PX4 heartbeats at 1 Hz: two periods


@dataclass
class Flight:
    ap: MockAutopilot
    link: MavlinkLink
    tracker: VehicleStateTracker
    cmds: VehicleCommands

    def controller(self, **kw: object) -> OffboardController:
        args: dict[str, object] = {"rate_hz": 30.0, "heartbeat_timeout_s": HB_TIMEOUT_S}
        args.update(kw)
        return OffboardController(self.link, self.tracker, self.cmds, **args)  # type: ignore[arg-type]

    async def wait(self, pred: Callable[[VehicleState], bool], what: str, timeout_s: float = 20.0) -> VehicleState:
        return await self.tracker.wait_for(pred, timeout_s, what)

    @property
    def ground_z_m(self) -> float:
        """Local NED z of home: PX4's local origin is not the floor (-0.86 m with GPS height)."""
        home = self.tracker.snapshot().home
        assert home is not None
        return home.position_ned_m[2]

    def ned(self, north_m: float, east_m: float, height_m: float) -> tuple[float, float, float]:
        """Local NED of a point ``height_m`` above home."""
        return (north_m, east_m, self.ground_z_m - height_m)

    def true_ned(self, local_ned_m: tuple[float, float, float]) -> tuple[float, float, float]:
        """A reported local NED point in the mock's floor-based truth frame (the reported
        height rises above the truth in Hold: ``Px4Behaviour.hold_sink_m_s``)."""
        n, e, d = local_ned_m
        return (n, e, d - self.ground_z_m + self.ap.height_error_m)

    async def take_off(self) -> None:
        await self.cmds.arm()
        await self.cmds.takeoff(TAKEOFF_ALT_M)
        top = self.ground_z_m - TAKEOFF_ALT_M + 0.15
        await self.wait(lambda s: s.in_air and s.position_ned_m is not None and s.position_ned_m[2] < top,
                        "takeoff height above home")
        # PX4 heartbeats at 1 Hz: only a heartbeat sent after the climb shows Hold for sure.
        await asyncio.sleep(1.1)
        await self.wait(lambda s: s.flight_mode is FlightMode.HOLD, "takeoff done, Hold")


def _near(target: tuple[float, float, float], tol_m: float) -> Callable[[VehicleState], bool]:
    return lambda s: s.position_ned_m is not None and math.dist(s.position_ned_m, target) < tol_m


@pytest_asyncio.fixture
async def flight() -> AsyncIterator[Flight]:
    async with MavlinkLink("udpin://127.0.0.1:0", heartbeat_rate_hz=2.0) as link:
        port = link.transport.local_address[1]  # type: ignore[attr-defined]
        # Brisk takeoff and landing keep the suite short; flight behaviour is unchanged.
        params = {"MPC_TKO_SPEED": 3.0, "MPC_LAND_SPEED": 2.0, "COM_DISARM_LAND": 0.3,
                  "MPC_ACC_HOR": 6.0}
        async with MockAutopilot(local_port=0, remote_ports=[port], params=params) as ap:
            tracker = VehicleStateTracker()
            tracker.attach(link)
            cmds = VehicleCommands(CommandSender(link, timeout_s=0.5, retries=3), tracker)
            f = Flight(ap, link, tracker, cmds)
            # PX4 has a home once its pre-flight checks pass: it can arm from then on.
            await f.wait(lambda s: s.home is not None and s.position_ned_m is not None
                         and s.heartbeat_fresh(HB_TIMEOUT_S), "first telemetry and home", 10.0)
            yield f


@pytest.mark.asyncio
async def test_telemetry_and_our_identity(flight: Flight) -> None:
    s = await flight.wait(lambda s: s.battery_v is not None and s.attitude_rpy_rad is not None, "telemetry")
    assert s.flight_mode is FlightMode.HOLD and not s.armed
    assert s.landed_state is LandedState.ON_GROUND
    assert s.home is not None and s.home.altitude_amsl_m == pytest.approx(flight.ap.home.alt_m)
    assert s.position_ned_m == pytest.approx((0.0, 0.0, s.home.position_ned_m[2]), abs=0.05)
    assert 0.0 < (s.battery_remaining or 0.0) <= 1.0
    await flight.ap.wait_until(lambda: (1, 191) in flight.ap.peer_heartbeats, 5.0, "our heartbeat")
    async with flight.link.subscribe("AUTOPILOT_VERSION") as versions:
        await flight.cmds.request_message(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        assert (await versions.get(3.0)).get_srcComponent() == 1
    await flight.cmds.set_message_interval(mavlink.MAVLINK_MSG_ID_ATTITUDE, 2.0)


@pytest.mark.asyncio
async def test_arm_takeoff_offboard_and_land(flight: Flight) -> None:
    await flight.take_off()
    target = flight.ned(1.0, 0.5, TAKEOFF_ALT_M)
    async with flight.controller() as ctl:
        ctl.set_setpoint(PositionSetpoint(target, yaw_rad=0.5, velocity_ned_m_s=(0.0, 0.0, 0.0)))
        await ctl.engage()
        assert ctl.state is OffboardState.ACTIVE
        # PX4's rule: setpoints streamed for at least 1 s before OFFBOARD was requested.
        set_mode = [r for r in flight.ap.commands.received(mavlink.MAV_CMD_DO_SET_MODE)
                    if int(r.params[1]) == FlightMode.OFFBOARD.main_mode][0]
        # (stamps are the mock's receive times: allow for loopback delivery differences)
        assert set_mode.stamp_s - flight.ap.setpoints[0].stamp_s >= 0.95
        s = await flight.wait(_near(target, 0.15), "offboard target")
        assert s.flight_mode is FlightMode.OFFBOARD
        await flight.wait(lambda s: abs(math.remainder((s.yaw_ned_rad or 0.0) - 0.5, math.tau)) < 0.1, "yaw")
        # Our map-frame pose back to PX4 as external vision lands in the autopilot's NED/FRD.
        _, T_map_body = flight.ap.T_map_body()
        flight.link.send(vision_odometry_message(flight.link, T_map_body, 42))
        await flight.ap.wait_until(lambda: any(v.time_usec == 42 for v in flight.ap.vision), 3.0, "vision")
        sample = [v for v in flight.ap.vision if v.time_usec == 42][0]
        yaw = 2.0 * math.atan2(sample.q_wxyz[3], sample.q_wxyz[0])
        assert abs(math.remainder(yaw - flight.ap.state().yaw_rad, math.tau)) < 0.05
        assert math.dist(sample.position_ned_m, flight.ap.position_ned_m) < 0.2
        await ctl.release(FlightMode.HOLD)
        assert ctl.state is OffboardState.IDLE
        assert all(t.new is not OffboardState.YIELDED for t in ctl.status().transitions)
    await flight.cmds.land()
    s = await flight.wait(lambda s: not s.armed, "landed and disarmed", 30.0)
    assert s.landed_state is LandedState.ON_GROUND


class _Uploader:
    """A ground station uploading a mission with the raw MISSION protocol (test setup only)."""

    def __init__(self, ap_port: int) -> None:
        self.ap_port = ap_port
        self.mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)

    async def upload(self, items: list[mavlink.MAVLink_mission_item_int_message]) -> None:
        loop = asyncio.get_running_loop()
        queue: asyncio.Queue[mavlink.MAVLink_message] = asyncio.Queue()
        parser = mavlink.MAVLink(None)

        class Proto(asyncio.DatagramProtocol):
            def datagram_received(self, data: bytes, addr: object) -> None:
                for m in parser.parse_buffer(data) or []:
                    queue.put_nowait(m)

        transport, _ = await loop.create_datagram_endpoint(Proto, remote_addr=("127.0.0.1", self.ap_port))
        try:
            def send(msg: mavlink.MAVLink_message) -> None:
                transport.sendto(msg.pack(self.mav))
                self.mav.seq = (self.mav.seq + 1) % 256

            send(self.mav.mission_count_encode(1, 1, len(items), mavlink.MAV_MISSION_TYPE_MISSION))
            async with asyncio.timeout(10.0):
                while True:
                    m = await queue.get()
                    if m.get_type() in ("MISSION_REQUEST_INT", "MISSION_REQUEST") and m.target_component == 190:
                        send(items[m.seq])
                    elif m.get_type() == "MISSION_ACK" and m.target_component == 190:
                        assert m.type == mavlink.MAV_MISSION_ACCEPTED
                        return
        finally:
            transport.close()


@pytest.mark.asyncio
async def test_mission_download_and_fly_it_leg_by_leg(flight: Flight) -> None:
    home = flight.tracker.snapshot().home
    assert home is not None
    legs_ned = [flight.ned(1.5, 0.0, TAKEOFF_ALT_M), flight.ned(1.5, 1.5, TAKEOFF_ALT_M), flight.ned(0.0, 1.5, 1.0)]
    m = mavlink.MAVLink(None)
    items = []
    for seq, (n, e, d) in enumerate(legs_ned):
        height_m = flight.ground_z_m - d
        lat = home.latitude_deg + math.degrees(n / 6378137.0)
        lon = home.longitude_deg + math.degrees(e / (6378137.0 * math.cos(math.radians(home.latitude_deg))))
        items.append(m.mission_item_int_encode(
            1, 1, seq, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mavlink.MAV_CMD_NAV_WAYPOINT,
            int(seq == 0), 1, 0.0, 0.3, 0.0, math.nan, round(lat * 1e7), round(lon * 1e7), height_m,
            mavlink.MAV_MISSION_TYPE_MISSION))
    await _Uploader(flight.ap.local_port).upload(items)

    mission = await download_mission(flight.link)
    assert [i.seq for i in mission] == [0, 1, 2]
    assert all(i.command == mavlink.MAV_CMD_NAV_WAYPOINT for i in mission)
    targets = [waypoint_ned_m(i, home) for i in mission]
    for got, want in zip(targets, legs_ned, strict=True):
        assert got == pytest.approx(want, abs=0.02)

    await flight.take_off()
    async with flight.controller() as ctl:
        ctl.set_setpoint(PositionSetpoint(targets[0]))
        await ctl.engage()
        for target in targets:
            ctl.set_setpoint(PositionSetpoint(target))
            await flight.wait(_near(target, 0.2), f"leg to {target}")
            assert math.dist(flight.ap.position_ned_m, flight.true_ned(target)) < 0.3
        await ctl.release(FlightMode.LAND)
    await flight.wait(lambda s: s.landed_state is LandedState.ON_GROUND, "landing", 30.0)


@pytest.mark.asyncio
async def test_pilot_switching_mode_is_not_fought(flight: Flight) -> None:
    await flight.take_off()
    async with flight.controller() as ctl:
        ctl.set_setpoint(PositionSetpoint(flight.ned(2.0, 0.0, TAKEOFF_ALT_M)))
        await ctl.engage()
        flight.ap.set_mode(FlightMode.POSCTL)  # the pilot flips the RC mode switch
        await flight.wait(lambda s: s.flight_mode is FlightMode.POSCTL, "pilot mode")
        await flight.ap.wait_until(lambda: ctl.state is OffboardState.YIELDED, 3.0, "yield")
        sent = ctl.status().setpoints_sent
        await asyncio.sleep(1.0)
        assert ctl.status().setpoints_sent == sent  # we stopped streaming
        assert flight.ap.mode is FlightMode.POSCTL  # and never asked for OFFBOARD again
        assert len([r for r in flight.ap.commands.received(mavlink.MAV_CMD_DO_SET_MODE)
                    if int(r.params[1]) == FlightMode.OFFBOARD.main_mode]) == 1
        # Told to, we take over again.
        await ctl.engage()
        assert flight.ap.mode is FlightMode.OFFBOARD and ctl.state is OffboardState.ACTIVE
        # Each request is dated, for judging where PX4 switched (it reports it a heartbeat later).
        assert len(ctl.mode_requests_s) == 2 and ctl.mode_requests_s[0] < ctl.mode_requests_s[1]


@pytest.mark.asyncio
async def test_link_loss_stops_commanding_until_told(flight: Flight) -> None:
    flight.ap.params.set("COM_OBL_RC_ACT", 5)  # PX4 holds on offboard loss (default: Position mode)
    await flight.take_off()
    async with flight.controller() as ctl:
        ctl.set_setpoint(PositionSetpoint(flight.ned(0.5, 0.0, TAKEOFF_ALT_M)))
        await ctl.engage()
        flight.ap.faults.drop_link = True
        await flight.ap.wait_until(lambda: ctl.state is OffboardState.LINK_LOST, 5.0, "link loss")
        assert "heartbeat lost" in ctl.status().reason
        sent = ctl.status().setpoints_sent
        # The mock sees no setpoints: PX4's own offboard-loss failsafe holds the vehicle.
        await flight.ap.wait_until(lambda: flight.ap.mode is FlightMode.HOLD, 5.0, "PX4 failsafe")
        flight.ap.faults.drop_link = False
        await flight.wait(lambda s: s.heartbeat_fresh(0.5) and s.flight_mode is FlightMode.HOLD, "link back")
        await asyncio.sleep(1.0)
        assert ctl.state is OffboardState.LINK_LOST  # no re-engage by itself
        assert ctl.status().setpoints_sent == sent
        assert flight.ap.mode is FlightMode.HOLD
        await ctl.engage()
        assert ctl.state is OffboardState.ACTIVE and flight.ap.mode is FlightMode.OFFBOARD


@pytest.mark.asyncio
async def test_setpoint_loss_hands_over_to_px4_failsafe(flight: Flight) -> None:
    await flight.take_off()
    ctl = flight.controller()
    async with ctl:
        ctl.set_setpoint(PositionSetpoint(flight.ned(0.0, 0.5, TAKEOFF_ALT_M)))
        await ctl.engage()
    # The controller closed while in OFFBOARD (say, the service stopped): no more setpoints.
    await flight.ap.wait_until(lambda: bool(flight.ap.failsafes), 5.0, "offboard loss failsafe")
    assert flight.ap.failsafes[-1].reason == "offboard setpoint loss"
    s = await flight.wait(lambda s: s.flight_mode is not FlightMode.OFFBOARD, "mode after failsafe")
    assert s.flight_mode is flight.ap.failsafes[-1].action
    assert ctl.state is OffboardState.IDLE


@pytest.mark.asyncio
async def test_stale_pose_holds_position(flight: Flight) -> None:
    await flight.take_off()
    pose_ok = True
    async with flight.controller(is_pose_fresh=lambda: pose_ok) as ctl:
        far = flight.ned(6.0, 0.0, TAKEOFF_ALT_M)
        ctl.set_setpoint(PositionSetpoint(far))
        await ctl.engage()
        await flight.wait(lambda s: s.position_ned_m is not None and s.position_ned_m[0] > 1.0, "moving north")
        pose_ok = False
        await flight.ap.wait_until(lambda: ctl.state is OffboardState.HOLDING, 3.0, "hold")
        hold = ctl.failsafe.hold
        assert hold is not None and hold.position_ned_m[0] < 5.0
        await flight.ap.wait_until(
            lambda: flight.ap.setpoints[-1].target.position_ned_m == pytest.approx(flight.true_ned(hold.position_ned_m),
                                                                                   abs=1e-4),
            3.0, "hold setpoint at the autopilot")
        # It brakes (overshooting by its stopping distance) and settles on the hold point,
        # never continuing to the 6 m target.
        max_north = [0.0]

        def settled() -> bool:
            max_north[0] = max(max_north[0], flight.ap.position_ned_m[0])
            return math.dist(flight.ap.position_ned_m, flight.true_ned(hold.position_ned_m)) < 0.15

        await flight.ap.wait_until(settled, 10.0, "settled on the hold point")
        assert max_north[0] < far[0] - 0.5  # it never went on to the target
        assert flight.ap.mode is FlightMode.OFFBOARD and ctl.state is OffboardState.HOLDING
        # Fresh again and a new plan: flying resumes.
        pose_ok = True
        back = flight.ned(0.0, 0.0, TAKEOFF_ALT_M)
        ctl.set_setpoint(PositionSetpoint(back))
        await flight.wait(_near(back, 0.25), "resumed")
        assert ctl.state is OffboardState.ACTIVE


@pytest.mark.asyncio
async def test_rejected_and_unanswered_commands(flight: Flight) -> None:
    await flight.cmds.arm()
    flight.ap.faults.ignore_commands = {mavlink.MAV_CMD_NAV_TAKEOFF}
    with pytest.raises(CommandTimeoutError) as timeout_info:
        await flight.cmds.takeoff(TAKEOFF_ALT_M)
    assert timeout_info.value.result == "TIMEOUT"
    assert len(flight.ap.commands.received(mavlink.MAV_CMD_NAV_TAKEOFF)) == 4  # 1 + 3 retries
    flight.ap.faults.ignore_commands = set()
    flight.ap.faults.reject_commands = {mavlink.MAV_CMD_DO_SET_MODE}
    async with flight.controller() as ctl:
        with pytest.raises(CommandDeniedError):
            await ctl.engage()  # streams a hold at the vehicle, then PX4 says no
        assert ctl.state is OffboardState.IDLE
        sent = ctl.status().setpoints_sent
        assert sent > 0
        await asyncio.sleep(0.3)
        assert ctl.status().setpoints_sent == sent
    flight.ap.faults.reject_commands = set()
    await flight.cmds.disarm()
    await flight.wait(lambda s: not s.armed, "disarmed")
    flight.ap.faults.prearm_fail = True
    with pytest.raises(CommandDeniedError) as info:
        await flight.cmds.arm()
    assert info.value.result == "DENIED"
    assert flight.tracker.snapshot().heartbeat_fresh(HB_TIMEOUT_S)  # the link survived it all


@pytest.mark.asyncio
async def test_garbage_on_the_socket_both_ways(flight: Flight) -> None:
    flight.ap.faults.corrupt_bytes_rate = 0.002
    for _ in range(20):
        flight.ap.inject_garbage(200)
        flight.link.transport.send(os.urandom(100))
        flight.link.transport.send(b"\xfd\x20" + os.urandom(40))
        await asyncio.sleep(0.02)
    await flight.cmds.arm()
    await flight.wait(lambda s: s.armed, "armed through the noise")
    assert flight.link.stats.bad_data > 0
    assert flight.ap.bad_packets > 0
    flight.ap.faults.corrupt_bytes_rate = 0.0
    await flight.cmds.disarm()
    await flight.wait(lambda s: not s.armed and s.heartbeat_fresh(0.5), "still talking")


@pytest.mark.asyncio
async def test_obstacle_distance_feed_reaches_the_autopilot(flight: Flight) -> None:
    spec = GridSpec(0.05, (-4.0, -4.0), (160, 160))
    cost = np.zeros(spec.shape_rc, dtype=np.uint8)
    X, _ = spec.cell_centers_xy()
    cost[(X > 1.5) & (X < 1.7)] = LETHAL_OBSTACLE  # a wall 1.5 m east of home
    costmap = Costmap(spec, cost, VerticalBand(0.5, 2.0))
    inp = ObstacleDistanceInput(costmap, (0.0, 0.0), 0.0)  # facing east, map frame
    async with ObstacleDistanceFeed(flight.link, lambda: inp, rate_hz=10.0) as feed:
        await flight.ap.wait_until(lambda: flight.ap.messages_received["OBSTACLE_DISTANCE"] >= 5,
                                   5.0, "OBSTACLE_DISTANCE")
        assert feed.sent >= 5
    msg = flight.ap.last_received["OBSTACLE_DISTANCE"]
    assert list(msg.distances) == list(compute_obstacle_distances(costmap, (0.0, 0.0), 0.0).distances_cm)
    assert msg.frame == mavlink.MAV_FRAME_BODY_FRD and msg.distances[0] == pytest.approx(150, abs=5)


@pytest.mark.asyncio
async def test_vehicle_stack_from_config(caplog: pytest.LogCaptureFixture, tmp_path: Path) -> None:
    cfg = LinkConfig(url="udpin://127.0.0.1:0", heartbeat_timeout_s=HB_TIMEOUT_S, setpoint_rate_hz=20.0,
                     obstacle_distance_rate_hz=10.0)
    spec = GridSpec(0.1, (-10.0, -10.0), (200, 200))  # clear beyond the 8 m range
    costmap = Costmap(spec, np.zeros(spec.shape_rc, dtype=np.uint8), VerticalBand(0.5, 2.0))
    caplog.set_level(logging.INFO, logger="companion.mavlink.vehicle")

    def source() -> ObstacleDistanceInput:
        return ObstacleDistanceInput(costmap, (0.0, 0.0), 0.0)

    async with Vehicle(cfg, obstacle_source=source, record_path=tmp_path / "run.tlog") as vehicle:
        port = vehicle.link.transport.local_address[1]  # type: ignore[attr-defined]
        async with MockAutopilot(local_port=0, remote_ports=[port]) as ap:
            s = await vehicle.wait_connected(10.0)
            assert s.flight_mode is FlightMode.HOLD and vehicle.connected
            assert await vehicle.download_mission() == ()
            await ap.wait_until(lambda: ap.messages_received["OBSTACLE_DISTANCE"] >= 3, 5.0, "feed")
            assert list(ap.last_received["OBSTACLE_DISTANCE"].distances) == [801] * 72  # free room
            # The vehicle answers PX4's TIMESYNC requests on time.monotonic: the autopilot
            # learns the offset between its boot clock and ours (to stamp our vision poses).
            await ap.wait_until(lambda: ap.peer_clock.offset_s is not None, 5.0, "timesync answer")
            assert vehicle.timesync.answered >= 1
            assert ap.peer_clock.offset_s == pytest.approx(ap.now_s() - time.monotonic(), abs=0.005)
            await vehicle.state.wait_for(lambda s: s.home is not None, 10.0, "home: PX4 ready to arm")
            await vehicle.commands.arm()
            await vehicle.offboard.engage()  # nothing planned: holds where it stands
            assert ap.mode is FlightMode.OFFBOARD
            await vehicle.offboard.release(FlightMode.HOLD)
            await vehicle.commands.disarm()
            ap.faults.drop_link = True
            await vehicle.state.wait_for(lambda s: not s.heartbeat_fresh(HB_TIMEOUT_S), 5.0, "loss")
            await ap.wait_until(lambda: "autopilot heartbeat lost" in caplog.text, 3.0, "watchdog log")
            assert not vehicle.connected
    assert not vehicle.link.is_open
    assert any(r.packet for r in iter_tlog(tmp_path / "run.tlog"))


@pytest.mark.asyncio
async def test_recorded_flight_replays_through_the_same_link(tmp_path: Path) -> None:
    tlog = tmp_path / "flight.tlog"
    async with MavlinkLink("udpin://127.0.0.1:0", record_path=tlog) as link:
        port = link.transport.local_address[1]  # type: ignore[attr-defined]
        async with MockAutopilot(local_port=0, remote_ports=[port]) as ap:
            live = VehicleStateTracker()
            live.attach(link)
            cmds = VehicleCommands(CommandSender(link), live)
            await live.wait_for(lambda s: s.home is not None, 10.0, "telemetry")
            await cmds.arm()
            await cmds.takeoff(1.0)
            # Heartbeats come at 1 Hz: wait for one that shows the vehicle armed and in Hold.
            await live.wait_for(lambda s: s.flight_mode is FlightMode.HOLD and s.in_air and s.armed, 20.0,
                                "airborne")
            ap.faults.drop_link = True  # freeze what gets recorded
            await asyncio.sleep(0.2)
            final = live.snapshot()
            received = link.stats.messages_received
    assert tlog.stat().st_size > 0

    async with MavlinkLink(f"tlog://{tlog}?speed=0", heartbeat_rate_hz=0) as replay:
        replayed = VehicleStateTracker()
        replayed.attach(replay)
        await asyncio.wait_for(replay.transport.finished.wait(), 30.0)  # type: ignore[attr-defined]
        again = replayed.snapshot()
        assert replay.stats.messages_received == received
        assert replay.stats.bad_data == 0
    assert again.flight_mode is FlightMode.HOLD and again.armed and again.in_air
    assert again.position_ned_m == final.position_ned_m
    assert again.home == final.home and again.battery_v == final.battery_v
