"""The service's stop always ends: a task of the service that swallows every cancellation is
left behind within the stop's bound, with every live task's stack and the worker processes'
state logged, and the parts after it still close (the map is saved)."""

from __future__ import annotations

import asyncio
import json
import logging
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

import companion.service.app as app
from companion.config import load_config
from companion.service.app import CompanionService
from companion.service.checkpoint import CHECKPOINT_NAME
from companion.sim.demo_e2e import LocalBroker, run_e2e
from companion.sim.sim_world import SimWorld

pytest.importorskip("open3d")

SMALL: dict[str, Any] = {
    "camera": {"width_px": 160, "height_px": 120, "fx_px": 96.0, "fy_px": 96.0, "cx_px": 80.0, "cy_px": 60.0},
    "sim": {"seed": 3, "room_width_m": 6.0, "room_depth_m": 5.0, "n_objects": 4, "layout": "scattered"},
}
#: The stubborn task gives up swallowing after this long: a stop that waited for it fails the test
#: here instead of hanging until pytest's timeout.
STUBBORN_CAP_S = 90.0


@pytest.mark.slow
def test_service_stop_ends_when_one_of_its_tasks_swallows_every_cancellation(
        tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(app, "TASK_STOP_TIMEOUT_S", 1.0)
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(json.loads(json.dumps(SMALL))))
    cfg = load_config(path)
    seen: dict[str, Any] = {}

    async def stubborn_hook(world: SimWorld, svc: CompanionService, broker: LocalBroker | None) -> None:
        await asyncio.sleep(2.0)
        svc.request_stop()
        t0 = time.monotonic()
        cancels = 0
        # Swallows its cancellation until the service has stopped (or the cap), as a loop with
        # ``suppress(CancelledError)`` around its await would.
        while svc.state != "stopped" and time.monotonic() - t0 < STUBBORN_CAP_S:
            try:
                await asyncio.sleep(0.05)
            except asyncio.CancelledError:
                cancels += 1
        seen["capped"] = svc.state != "stopped"
        seen["cancels"] = cancels

    with caplog.at_level(logging.ERROR):
        result = asyncio.run(run_e2e(cfg, tmp_path / "out", use_broker=False, timeout_s=60.0, inject=stubborn_hook))
    assert result.report is not None
    assert seen["capped"] is False, "the stop waited for the task that swallows its cancellation"
    assert seen["cancels"] >= 2  # cancelled again after it swallowed the first
    assert result.report.stop_overruns == ["stopping the service's tasks overran 1 s"]
    msg = "\n".join(r.getMessage() for r in caplog.records)
    assert "task 'on-active' did not end within 1.0 s" in msg
    assert "stubborn_hook" in msg  # its stack says where it is stuck
    assert "worker perception: pid" in msg and "worker planner: pid" in msg
    # The parts after the stuck task still closed: the perception process saved the map.
    assert list((tmp_path / "out").rglob(CHECKPOINT_NAME))
    assert result.summary["frames"]["processed"] > 0
