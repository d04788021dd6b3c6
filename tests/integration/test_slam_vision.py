"""External vision over our own link to the mock PX4: recorded, fused, and what it fixes.

The mock's odometry drifts (heading 4 deg/s here, so a few seconds show it); our
:class:`VisionStream` sends a pose at 30 Hz; the mock records every ODOMETRY message and
its estimator fuses them, so its reported pose (what the link's telemetry shows) comes back
to the truth and offboard setpoints are flown where they are meant.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import AsyncIterator
from dataclasses import dataclass

import numpy as np
import pytest
import pytest_asyncio

from companion.mavlink.commands import CommandSender, VehicleCommands
from companion.mavlink.failsafe import PositionSetpoint
from companion.mavlink.link import MavlinkLink
from companion.mavlink.offboard import OffboardController
from companion.mavlink.state import VehicleState, VehicleStateTracker
from companion.mavlink.vision import VisionPose, VisionStream
from companion.px4 import FlightMode
from companion.sim.autopilot import MockAutopilot
from companion.sim.odometry import OdometryDriftModel

pytestmark = pytest.mark.timeout(120)

ALT_M = 1.0


@dataclass
class Rig:
    ap: MockAutopilot
    link: MavlinkLink
    tracker: VehicleStateTracker
    cmds: VehicleCommands

    async def wait(self, pred: object, what: str, timeout_s: float = 20.0) -> VehicleState:
        return await self.tracker.wait_for(pred, timeout_s, what)  # type: ignore[arg-type]

    @property
    def ground_z_m(self) -> float:
        """Local NED z of home: PX4's local origin is not the floor."""
        home = self.tracker.snapshot().home
        assert home is not None
        return home.position_ned_m[2]

    def true_ned(self, local_ned_m: tuple[float, float, float]) -> tuple[float, float, float]:
        """A reported local NED point in the mock's floor-based truth frame (the reported
        height rises above the truth in Hold: ``Px4Behaviour.hold_sink_m_s``)."""
        n, e, d = local_ned_m
        return (n, e, d - self.ground_z_m + self.ap.height_error_m)

    async def take_off(self) -> None:
        await self.cmds.arm()
        await self.cmds.takeoff(ALT_M)
        top = self.ground_z_m - ALT_M + 0.15
        await self.wait(lambda s: s.in_air and s.position_ned_m is not None and s.position_ned_m[2] < top,
                        "takeoff height above home")
        await asyncio.sleep(1.1)  # PX4 heartbeats at 1 Hz: the next one shows the take-off done
        await self.wait(lambda s: s.flight_mode is FlightMode.HOLD, "takeoff done, Hold")


@pytest_asyncio.fixture
async def rig() -> AsyncIterator[Rig]:
    drift = OdometryDriftModel(scale_error=0.05, heading_drift_deg_s=4.0, noise_m_per_sqrt_m=0.0,
                               noise_rad_per_sqrt_rad=0.0, seed=3)
    async with MavlinkLink("udpin://127.0.0.1:0", heartbeat_rate_hz=2.0) as link:
        port = link.transport.local_address[1]  # type: ignore[attr-defined]
        params = {"MPC_TKO_SPEED": 3.0, "MPC_ACC_HOR": 6.0, "COM_DISARM_PRFLT": -1.0}
        async with MockAutopilot(local_port=0, remote_ports=[port], params=params, odometry_drift=drift,
                                 vision_gain=0.5) as ap:
            tracker = VehicleStateTracker()
            tracker.attach(link)
            cmds = VehicleCommands(CommandSender(link, timeout_s=0.5, retries=3), tracker)
            r = Rig(ap, link, tracker, cmds)
            await r.wait(lambda s: s.home is not None and s.position_ned_m is not None, "telemetry", 10.0)
            yield r


def _yaw_error_deg(reported_ned: float | None, true_ned: float) -> float:
    return abs(math.degrees(math.remainder((reported_ned or 0.0) - true_ned, math.tau)))


def _truth_pose(ap: MockAutopilot) -> VisionPose:
    # A perfect SLAM: the true pose, stamped on the vehicle clock the mock fuses by.
    stamp, T = ap.T_map_body()
    return VisionPose(stamp, np.asarray(T))


@pytest.mark.asyncio
async def test_mock_records_and_fuses_the_vision_stream(rig: Rig) -> None:
    ap = rig.ap
    await rig.take_off()
    await asyncio.sleep(1.0)
    # The link sees the drifting estimate, not the truth.
    s = rig.tracker.snapshot()
    assert _yaw_error_deg(s.yaw_ned_rad, ap.state().yaw_rad) > 5.0
    async with VisionStream(rig.link, lambda: _truth_pose(ap), rate_hz=30.0) as stream:
        await asyncio.sleep(1.5)
        n0, t0 = len(ap.vision), ap.now_s()
        await asyncio.sleep(1.0)
        rate = (len(ap.vision) - n0) / (ap.now_s() - t0)
        await rig.wait(lambda s: _yaw_error_deg(s.yaw_ned_rad, ap.state().yaw_rad) < 1.5, "the estimate to converge", 5.0)
        s = rig.tracker.snapshot()
        assert s.position_ned_m is not None
        assert math.dist(rig.true_ned(s.position_ned_m), ap.position_ned_m) < 0.05
        # Offboard with vision: the vehicle goes where it was told.
        target = (1.5, -1.0, rig.ground_z_m - ALT_M)
        async with OffboardController(rig.link, rig.tracker, rig.cmds, rate_hz=30.0) as ctl:
            ctl.set_setpoint(PositionSetpoint(target, yaw_rad=0.0))
            await ctl.engage()
            await ap.wait_until(lambda: math.dist(ap.position_ned_m, rig.true_ned(target)) < 0.1, 15.0,
                                "the true target")
            await ctl.release(FlightMode.HOLD)
    assert stream.sent > 60
    assert 20.0 < rate < 40.0
    last = ap.vision[-1]
    assert last.msg_type == "ODOMETRY"
    assert ap.estimator.vision_fused > 10


@pytest.mark.asyncio
async def test_without_vision_the_drift_moves_the_vehicle_off_target(rig: Rig) -> None:
    # The same flight with no vision: PX4 flies its drifting estimate to the setpoint.
    ap = rig.ap
    await rig.take_off()
    target = (2.0, 0.0, rig.ground_z_m - ALT_M)
    async with OffboardController(rig.link, rig.tracker, rig.cmds, rate_hz=30.0) as ctl:
        ctl.set_setpoint(PositionSetpoint(target, yaw_rad=0.0))
        await ctl.engage()
        await rig.wait(lambda s: s.position_ned_m is not None and math.dist(s.position_ned_m, target) < 0.05,
                       "the reported pose on the target")
        await asyncio.sleep(1.0)
        await ctl.release(FlightMode.HOLD)
    assert math.dist(ap.position_ned_m, rig.true_ned(target)) > 0.1
    assert ap.estimator.vision_fused == 0
