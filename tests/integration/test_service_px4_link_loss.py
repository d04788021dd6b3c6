"""A link loss with PX4's default offboard-loss action: the vehicle lands by itself, and the
service, when the link comes back, must not engage OFFBOARD on the ground."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from companion.config import load_config
from companion.mavlink.failsafe import OffboardState
from companion.service.app import CompanionService
from companion.sim.demo_e2e import LocalBroker, run_e2e
from companion.sim.sim_world import SimWorld

pytest.importorskip("open3d")

SMALL: dict[str, Any] = {
    "camera": {"width_px": 160, "height_px": 120, "fx_px": 96.0, "fy_px": 96.0, "cx_px": 80.0, "cy_px": 60.0},
    "sim": {"seed": 3, "room_width_m": 6.0, "room_depth_m": 5.0, "n_objects": 4},
}


@pytest.mark.slow
def test_vehicle_landed_by_px4s_failsafe_is_not_engaged_again(tmp_path: Path) -> None:
    """With COM_OBL_RC_ACT 0 (Position mode, no RC) PX4 descends, lands and disarms during a
    3 s link loss. The service used to re-engage OFFBOARD when the link came back, which PX4
    accepts on the ground, disarmed."""
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(json.loads(json.dumps(SMALL))))
    cfg = load_config(path)
    seen: dict[str, Any] = {}

    async def inject(world: SimWorld, svc: CompanionService, broker: LocalBroker | None) -> None:
        ap = world.autopilot
        deadline = time.monotonic() + 60.0
        while not (svc.vehicle is not None and svc.vehicle.offboard.state is OffboardState.ACTIVE):
            assert time.monotonic() < deadline, "never engaged"
            await asyncio.sleep(0.05)
        await asyncio.sleep(1.0)
        ap.faults.drop_link = True
        deadline = time.monotonic() + 15.0
        while ap.armed:
            assert time.monotonic() < deadline, "PX4's failsafe did not land the vehicle"
            await asyncio.sleep(0.05)
        landed_at = time.monotonic()
        await asyncio.sleep(0.5)
        ap.faults.drop_link = False
        await asyncio.sleep(5.0)
        assert svc.vehicle is not None
        seen["engages_after_landing"] = [t for t in svc.vehicle.offboard.failsafe.transitions
                                         if t.at_s > landed_at and t.new is OffboardState.WARMUP]
        seen["armed"] = ap.armed

    result = asyncio.run(run_e2e(cfg, tmp_path / "out", timeout_s=90.0, inject=inject))
    s = result.summary
    assert seen["engages_after_landing"] == [], seen
    assert seen["armed"] is False
    assert s["mission_error"] is not None and "landed during the link loss" in s["mission_error"]
