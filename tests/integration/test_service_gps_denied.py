"""The service as PX4's only position source: the mock autopilot without GPS (its horizontal
position comes only from the SLAM pose the service sends), a mission flown on it, and the SLAM
lost mid-flight (the camera stops): the vehicle holds on the autopilot's estimate and resumes,
or, lost for longer, lands before the autopilot's own estimate runs out."""

from __future__ import annotations

import asyncio
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from companion.config import load_config
from companion.mavlink.failsafe import OffboardState
from companion.service.app import CompanionService
from companion.sim.demo_e2e import run_e2e
from companion.sim.sim_world import SimWorld

#: Closed-loop flights, as tests/integration/test_service_slam.py: the full suite runs them.
pytest.importorskip("open3d")

SMALL: dict[str, Any] = {
    # The camera 0.1 m above the body's origin, which rests on the floor: without GPS the
    # vehicle must localize before it may arm, and a camera at floor level sees nothing.
    "camera": {"width_px": 160, "height_px": 120, "fx_px": 96.0, "fy_px": 96.0, "cx_px": 80.0, "cy_px": 60.0,
               "extrinsics": {"xyz_m": [0.1, 0.0, 0.1], "rpy_deg": [0.0, 0.0, 0.0]}},
    # Scattered furniture: what these tests fly is the loss of the position source; in a
    # realistic room the shipped detector's phantoms can close the mission's passage
    # (bench/mapping.py measures that).
    "sim": {"seed": 3, "room_width_m": 6.0, "room_depth_m": 5.0, "n_objects": 4, "gps_denied": True,
            "layout": "scattered"},
    "service": {"localization": "slam"},
    "link": {"external_vision": True, "vision_is_position_source": True},
}


def _cfg(tmp_path: Path, **link: float) -> Any:
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump({**SMALL, "link": {**SMALL["link"], **link}}))
    return load_config(path)


async def _until(pred: Any, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.05)


def _flying_a_leg(svc: CompanionService) -> bool:
    return (svc.vehicle is not None and svc.vehicle.offboard.state is OffboardState.ACTIVE
            and svc.runner is not None and len(svc.runner.reports) >= 1)


async def _lose_slam(world: SimWorld, svc: CompanionService, seconds: float, out: dict[str, Any]) -> None:
    """The camera (and with it the SLAM) stops for ``seconds`` during the second leg; records
    whether the vehicle held, how far it drifted once stopped, and the estimate's error."""
    await _until(lambda: _flying_a_leg(svc), 90.0)
    ap = world.autopilot
    world.camera_missing = True
    t0, moved, held_at = time.monotonic(), 0.0, None
    while time.monotonic() - t0 < seconds:
        await asyncio.sleep(0.05)
        holding = svc.vehicle is not None and svc.vehicle.offboard.state is OffboardState.HOLDING
        if holding and held_at is None:
            held_at = (time.monotonic(), np.array(ap.position_ned_m))
        if held_at is not None and time.monotonic() - held_at[0] > 1.0:  # braked from cruise speed
            moved = max(moved, float(np.linalg.norm(np.array(ap.position_ned_m)[:2] - held_at[1][:2])))
    held = held_at is not None
    world.camera_missing = False
    est = ap.estimated_state().position_ned_m
    out.update(held=held, moved_m=moved, est_err_m=math.dist(est[:2], ap.position_ned_m[:2]))


@pytest.mark.slow
def test_a_mission_flown_on_the_slam_pose_alone_survives_two_seconds_without_it(tmp_path: Path) -> None:
    cfg = _cfg(tmp_path)
    out: dict[str, Any] = {}

    async def inject(world: SimWorld, svc: CompanionService, broker: Any) -> None:
        assert world.autopilot.aiding.active
        # Shorter than the landing deadline at the flight altitude (3.1 s at 0.6 m with PX4's
        # EKF2_NOAID_TOUT 5 s), pipeline latency included: the flight goes on.
        await _lose_slam(world, svc, 2.0, out)

    result = asyncio.run(run_e2e(cfg, tmp_path / "out", use_broker=False, timeout_s=150.0, inject=inject))
    s = result.summary
    loc = result.report.localization  # type: ignore[union-attr]
    detail = f"{out}, {loc}, {s['legs']}"
    assert s["collisions"] == 0, detail
    # Held within a second of losing the SLAM, stood still on PX4's estimate, went on once it was back.
    assert out["held"], detail
    assert out["moved_m"] < 0.3, detail
    actions = loc["vision_loss_actions"].split(",")
    assert "hold" in actions and actions[actions.index("hold") + 1] == "resume", detail
    assert loc["vision_gap_resets"] >= 1, detail
    # The legs before and after the loss were flown. Later the SLAM may lose its match again on
    # its own (the return leg faces the doorway, with few walls in the scan band): then the
    # service lands before the autopilot runs out of position, never flies on without it.
    assert s["waypoints_reached"] >= 2, detail
    assert all(b in ("resume", "land") for a, b in zip(actions, actions[1:], strict=False) if a == "hold"), detail
    assert s["waypoints_reached"] == s["waypoints_total"] or actions[-1] == "land", detail
    assert s["autopilot_failsafes"] == [], detail  # PX4's no-position failsafe never had to act


@pytest.mark.slow
def test_the_slam_lost_for_longer_lands_before_the_autopilot_loses_its_position(tmp_path: Path) -> None:
    cfg = _cfg(tmp_path)
    out: dict[str, Any] = {}

    async def inject(world: SimWorld, svc: CompanionService, broker: Any) -> None:
        out["world"] = world  # read after the flight: the landing ends the mission and this task
        await _lose_slam(world, svc, 7.0, out)

    result = asyncio.run(run_e2e(cfg, tmp_path / "out", use_broker=False, timeout_s=150.0, inject=inject))
    s = result.summary
    loc = result.report.localization  # type: ignore[union-attr]
    detail = f"{out}, {loc}"
    assert loc["vision_loss_actions"].endswith("hold,land"), detail
    assert s["autopilot_failsafes"] == [], detail  # PX4's own no-position failsafe never had to act
    final = s["autopilot_final"]
    assert "LAND" in final["modes"] and not final["in_air"], f"{detail}, {final}"
    text = out["world"].autopilot.last_received["STATUSTEXT"].text
    assert text.startswith("SLAM lost") and "landing" in text, detail
    assert s["collisions"] == 0, detail
