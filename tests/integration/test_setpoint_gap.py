"""The longest setpoint gap in the demo's summary is the one the autopilot saw: a stream that
stopped (here: until PX4's offboard-loss failsafe) counts, though no setpoint closed the gap."""

from __future__ import annotations

import asyncio

import pytest

from companion.mavlink.link import MavlinkLink
from companion.px4 import FlightMode
from companion.sim.autopilot import MockAutopilot
from companion.sim.demo_e2e import setpoint_gap_stats_ms


@pytest.mark.asyncio
async def test_a_stream_that_stops_in_offboard_is_the_longest_gap() -> None:
    async with MockAutopilot(local_port=0, remote_ports=()) as ap:
        loss_s = ap.params.get("COM_OF_LOSS_T")
        async with MavlinkLink(f"udpout://127.0.0.1:{ap.local_port}", heartbeat_rate_hz=2.0) as link:
            for i in range(30):
                link.send(link.mav.set_position_target_local_ned_encode(
                    link.time_boot_ms(), 1, 1, 1, 0b0000_1111_1111_1000, 0.0, 0.0, -1.0, 0, 0, 0, 0, 0, 0, 0, 0))
                if i == 10:
                    ap.arm()  # PX4's offboard-loss failsafe acts only while armed
                    ap.set_mode(FlightMode.OFFBOARD)
                await asyncio.sleep(1.0 / 30.0)
            await ap.wait_until(lambda: ap.mode is not FlightMode.OFFBOARD, 5.0 + loss_s)
        stamps = [sp.stamp_s for sp in ap.setpoints]
    assert setpoint_gap_stats_ms(stamps)["max_ms"] < loss_s * 1e3  # the receive stamps alone miss it
    stats = setpoint_gap_stats_ms(stamps, ap.offboard_gap_max_s)
    assert stats["max_ms"] >= loss_s * 1e3 and stats["offboard_max_ms"] == stats["max_ms"]
    assert stats["over_100ms"] >= 1
