"""The planner worker killed while starting, while idle between requests and before close:
replaced, logged as a warning, never a hang."""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import signal
import threading
import time

import numpy as np
import pytest

from planner.config import PlannerConfig
from planner.worker import PlanningService
from semmap.costmap import FREE_SPACE, LETHAL_OBSTACLE, Costmap, VerticalBand
from semmap.grid import GridSpec

SPEC = GridSpec(0.05, (0.0, 0.0), (60, 120))
CONFIG = PlannerConfig(vehicle_radius_m=0.2, time_limit_s=0.2)


def _costmap() -> Costmap:
    cost = np.full(SPEC.shape_rc, FREE_SPACE, dtype=np.uint8)
    cost[0, :] = cost[-1, :] = cost[:, 0] = cost[:, -1] = LETHAL_OBSTACLE
    band = VerticalBand.for_altitude(CONFIG.flight_altitude_m, CONFIG.vehicle_height_m, CONFIG.vertical_margin_m)
    return Costmap(SPEC, cost, band)


def _dead_planner_warnings(caplog: pytest.LogCaptureFixture) -> list[logging.LogRecord]:
    return [r for r in caplog.records if "planning worker" in r.getMessage()
            and ("died" in r.getMessage() or "killed" in r.getMessage())]


def test_a_worker_killed_while_starting_is_started_once_more(caplog: pytest.LogCaptureFixture) -> None:
    def kill_first_worker() -> None:
        end = time.monotonic() + 60.0
        while time.monotonic() < end:
            for p in mp.active_children():
                if p.name == "planner-worker" and p.pid is not None:
                    os.kill(p.pid, signal.SIGKILL)
                    return
            time.sleep(0.002)

    killer = threading.Thread(target=kill_first_worker, daemon=True)
    killer.start()
    with caplog.at_level(logging.WARNING, logger="planner.worker"), PlanningService(CONFIG) as svc:
        killer.join(5.0)
        assert svc.starts == 1 and svc.running
        assert svc.plan(_costmap(), 1, (1.0, 1.5), (5.0, 1.5)).ok
    warnings = _dead_planner_warnings(caplog)
    assert warnings and all(r.levelno == logging.WARNING for r in warnings)


def test_a_worker_killed_between_requests_is_replaced_with_a_warning(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="planner.worker"), PlanningService(CONFIG) as svc:
        assert svc.plan(_costmap(), 1, (1.0, 1.5), (5.0, 1.5)).ok
        os.kill(svc._proc.pid, signal.SIGKILL)  # noqa: SLF001 - the test kills the real worker
        time.sleep(0.2)
        assert svc.plan(_costmap(), 1, (1.0, 1.5), (5.0, 1.5)).ok
        assert svc.starts == 2
        # Killed again, then closed (the service stopping): close returns at once.
        os.kill(svc._proc.pid, signal.SIGKILL)  # noqa: SLF001
        t0 = time.monotonic()
    assert time.monotonic() - t0 < 3.0
    warnings = _dead_planner_warnings(caplog)
    assert warnings and all(r.levelno == logging.WARNING for r in warnings)
