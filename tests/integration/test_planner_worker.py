"""The planning service in a real separate process: caching, replanning, timeouts, bad input."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from planner.config import PlannerConfig
from planner.types import PlanStatus
from planner.worker import PlanningService
from semmap.costmap import FREE_SPACE, LETHAL_OBSTACLE, Costmap, ObjectFootprint, VerticalBand
from semmap.errors import PlanningError
from semmap.grid import GridSpec
from semmap.layers import paint_objects

SPEC = GridSpec(0.05, (0.0, 0.0), (60, 120))
#: Length-only objective with plain RRT*: on an open map the straight first path is optimal, so
#: RRT* can never beat it and always uses its whole budget (what the timeout and cancel tests
#: rely on; informed planners notice that the informed set is empty and stop early).
CONFIG = PlannerConfig(vehicle_radius_m=0.2, time_limit_s=0.2, cost_weight=0.0, algorithm="rrtstar")
BAND = VerticalBand.for_altitude(CONFIG.flight_altitude_m, CONFIG.vehicle_height_m, CONFIG.vertical_margin_m)


def base() -> Costmap:
    cost = np.full(SPEC.shape_rc, FREE_SPACE, dtype=np.uint8)
    cost[0, :] = cost[-1, :] = cost[:, 0] = cost[:, -1] = LETHAL_OBSTACLE
    return Costmap(SPEC, cost, BAND)


def with_chair() -> Costmap:
    poly = np.array([[2.7, 1.1], [3.3, 1.1], [3.3, 1.9], [2.7, 1.9]])
    return paint_objects(base(), [ObjectFootprint(1, "chair", poly, 0.0, 0.9)], BAND)


@pytest.fixture(scope="module")
def service():
    with PlanningService(CONFIG, timeout_slack_s=10.0) as svc:
        yield svc


def test_plans_caches_map_and_replans_after_change(service: PlanningService) -> None:
    sent = service.maps_sent
    r1 = service.plan(base(), 1, (1.0, 1.5), (5.0, 1.5))
    assert r1.ok and r1.map_version == 1
    assert r1.length_m == pytest.approx(4.0, abs=1e-6)
    r2 = service.plan(base(), 1, (1.0, 1.4), (5.0, 1.6))
    assert r2.ok and service.maps_sent == sent + 1  # version 1 cached in the worker
    r3 = service.plan(with_chair(), 2, (1.0, 1.5), (5.0, 1.5))
    assert r3.ok and r3.map_version == 2 and service.maps_sent == sent + 2
    assert r3.length_m > 4.05
    dense = np.concatenate([np.linspace(a, b, 50) for a, b in zip(r3.path_xy_m[:-1], r3.path_xy_m[1:], strict=True)])
    inside = (dense[:, 0] > 2.7) & (dense[:, 0] < 3.3) & (dense[:, 1] > 1.1) & (dense[:, 1] < 1.9)
    assert not inside.any()


def test_no_path_is_a_result(service: PlanningService) -> None:
    r = service.plan(base(), 1, (1.0, 1.5), (9.0, 1.5))
    assert r.status is PlanStatus.GOAL_OUTSIDE_MAP and "outside" in r.reason


def test_bad_request_raises_and_service_keeps_running(service: PlanningService) -> None:
    with pytest.raises(PlanningError, match="goal"):
        service.plan(base(), 1, (1.0, 1.5), (float("nan"), 1.5))
    assert service.plan(base(), 1, (1.0, 1.5), (5.0, 1.5)).ok


def test_timeout_kills_worker_and_next_request_recovers(service: PlanningService) -> None:
    starts = service.starts
    r = service.plan(base(), 3, (1.0, 0.5), (5.0, 2.5), time_limit_s=5.0, timeout_s=0.5)
    assert r.status is PlanStatus.TIMEOUT and not r.ok
    assert not service.running
    ok = service.plan(base(), 3, (1.0, 0.5), (5.0, 2.5))
    assert ok.ok and service.starts == starts + 1


def test_cancel_from_another_thread(service: PlanningService) -> None:
    service.plan(base(), 4, (1.0, 1.5), (5.0, 1.5))  # warm: map cached
    timer = threading.Timer(0.3, service.cancel)
    timer.start()
    t0 = time.monotonic()
    r = service.plan(base(), 4, (1.0, 0.5), (5.0, 2.5), time_limit_s=20.0)
    timer.cancel()
    assert r.status is PlanStatus.TIMEOUT
    assert time.monotonic() - t0 < 15.0


def test_path_checks_and_escape_points_are_answered_by_the_worker(service: PlanningService) -> None:
    through_chair = np.array([[1.0, 1.5], [5.0, 1.5]])
    beside_chair = np.array([[1.0, 0.5], [5.0, 0.5]])
    assert service.path_free(base(), 1, through_chair) is True
    assert service.path_free(with_chair(), 2, through_chair) is False
    assert service.path_free(with_chair(), 2, beside_chair) is True
    # From inside the chair, the nearest point where the vehicle fits lies outside it, with
    # the vehicle's radius to spare.
    esc = service.escape_point(with_chair(), 2, (3.0, 1.5))
    assert esc is not None
    assert not (2.7 - CONFIG.vehicle_radius_m < esc[0] < 3.3 + CONFIG.vehicle_radius_m
                and 1.1 - CONFIG.vehicle_radius_m < esc[1] < 1.9 + CONFIG.vehicle_radius_m)
    assert np.linalg.norm(esc - (3.0, 1.5)) < 1.0
    assert service.path_free(with_chair(), 2, np.vstack([esc, esc + (0.0, 0.05)])) is True
