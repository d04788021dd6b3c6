"""Planner on hand-made maps: the altitude rule, rejected goals, no-path results, replanning."""

from __future__ import annotations

import numpy as np
import pytest

from planner.config import PlannerConfig
from planner.planner import Planner, remaining_path
from planner.types import PlanStatus, path_length_m
from semmap.costmap import FREE_SPACE, LETHAL_OBSTACLE, Costmap, ObjectFootprint
from semmap.errors import PlanningError
from semmap.grid import GridSpec

SPEC = GridSpec(0.05, (0.0, 0.0), (60, 120))  # 6 m (x) by 3 m (y)


def rect(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)


def base_map(planner: Planner) -> Costmap:
    cost = np.full(SPEC.shape_rc, FREE_SPACE, dtype=np.uint8)
    cost[0, :] = cost[-1, :] = LETHAL_OBSTACLE
    cost[:, 0] = cost[:, -1] = LETHAL_OBSTACLE
    return Costmap(SPEC, cost, planner.band)


def make(altitude_m: float, **kw: object) -> Planner:
    settings: dict[str, object] = {"vehicle_radius_m": 0.2, "time_limit_s": 0.15, **kw}
    cfg = PlannerConfig(flight_altitude_m=altitude_m, **settings)  # type: ignore[arg-type]
    return Planner(cfg)


COFFEE = ObjectFootprint(1, "coffee_table", rect(2.5, 1.1, 3.5, 1.9), z_min_m=0.0, z_max_m=0.45)
#: A desk spanning the whole 3 m width: a wall at low altitude, nothing at 1.5 m.
LONG_DESK = ObjectFootprint(2, "desk", rect(2.6, -0.5, 3.4, 3.5), z_min_m=0.0, z_max_m=0.75)


def _assert_free_path(pl: Planner, result) -> None:
    assert result.ok, result.reason
    assert pl.cspace.path_free(result.path_xy_m)
    assert result.length_m == pytest.approx(path_length_m(result.path_xy_m))


def test_flies_straight_over_coffee_table_at_1_5_m() -> None:
    pl = make(1.5)
    pl.set_base_map(base_map(pl), [COFFEE])
    r = pl.plan((1.0, 1.5), (5.0, 1.5))
    _assert_free_path(pl, r)
    assert r.length_m == pytest.approx(4.0, abs=1e-6)


def test_goes_around_coffee_table_at_0_3_m() -> None:
    pl = make(0.3)
    pl.set_base_map(base_map(pl), [COFFEE])
    r = pl.plan((1.0, 1.5), (5.0, 1.5))
    _assert_free_path(pl, r)
    assert r.length_m > 4.1
    # Never between the legs: no path point inside the footprint.
    inside = (r.path_xy_m[:, 0] > 2.5) & (r.path_xy_m[:, 0] < 3.5) & (r.path_xy_m[:, 1] > 1.1) & (r.path_xy_m[:, 1] < 1.9)
    assert not inside.any()
    dense = pl.cspace.densify(r.path_xy_m)
    inside = (dense[:, 0] > 2.5) & (dense[:, 0] < 3.5) & (dense[:, 1] > 1.1) & (dense[:, 1] < 1.9)
    assert not inside.any()


def test_desk_cannot_be_flown_under_at_0_5_m() -> None:
    pl = make(0.5)
    pl.set_base_map(base_map(pl), [LONG_DESK])
    r = pl.plan((1.0, 1.5), (5.0, 1.5))
    assert r.status is PlanStatus.DISCONNECTED
    assert "separate free regions" in r.reason
    assert r.path_xy_m.shape == (0, 2)


def test_desk_can_be_flown_over_at_1_5_m() -> None:
    pl = make(1.5)
    pl.set_base_map(base_map(pl), [LONG_DESK])
    r = pl.plan((1.0, 1.5), (5.0, 1.5))
    _assert_free_path(pl, r)


def test_goal_outside_map_rejected_with_message() -> None:
    pl = make(0.5)
    pl.set_map(base_map(pl))
    r = pl.plan((1.0, 1.5), (9.0, 1.5))
    assert r.status is PlanStatus.GOAL_OUTSIDE_MAP
    assert "9.00" in r.reason and "outside" in r.reason


def test_goal_inside_obstacle_rejected_and_snapped_on_request() -> None:
    pl = make(0.3)
    pl.set_base_map(base_map(pl), [COFFEE])
    r = pl.plan((1.0, 1.5), (3.0, 1.5))
    assert r.status is PlanStatus.GOAL_BLOCKED
    assert "clearance" in r.reason
    s = pl.plan((1.0, 1.5), (3.0, 1.5), snap_goal=True)
    _assert_free_path(pl, s)
    assert s.snapped_goal
    goal = np.array(s.goal_xy_m)
    assert pl.cspace.is_free(goal[None])[0]
    # The snapped goal is the free point nearest the request: just outside the inflated table.
    assert np.linalg.norm(goal - np.array([3.0, 1.5])) < 0.8


def test_outside_goal_snaps_into_map() -> None:
    pl = make(0.5, snap_goal_to_free=True)
    pl.set_map(base_map(pl))
    r = pl.plan((1.0, 1.5), (9.0, 1.5))
    _assert_free_path(pl, r)
    assert r.snapped_goal and r.goal_xy_m is not None and r.goal_xy_m[0] > 5.0


def test_unreachable_goal_snaps_to_reachable_side() -> None:
    pl = make(0.5)
    pl.set_base_map(base_map(pl), [LONG_DESK])
    r = pl.plan((1.0, 1.5), (5.0, 1.5), snap_goal=True)
    _assert_free_path(pl, r)
    assert r.snapped_goal and r.goal_xy_m is not None and r.goal_xy_m[0] < 2.6


def test_start_blocked_and_outside() -> None:
    pl = make(0.3)
    pl.set_base_map(base_map(pl), [COFFEE])
    r = pl.plan((3.0, 1.5), (5.0, 1.5))
    assert r.status is PlanStatus.START_BLOCKED and not r.ok
    r = pl.plan((-2.0, 1.5), (5.0, 1.5))
    assert r.status is PlanStatus.START_OUTSIDE_MAP


def test_bad_input_is_an_error_not_a_result() -> None:
    pl = make(0.5)
    with pytest.raises(PlanningError, match="no map"):
        pl.plan((1.0, 1.0), (2.0, 2.0))
    pl.set_map(base_map(pl))
    with pytest.raises(PlanningError, match="goal"):
        pl.plan((1.0, 1.0), (float("nan"), 2.0))


@pytest.mark.parametrize("algorithm", ["informed_rrtstar", "bitstar", "rrtstar", "rrtconnect"])
def test_every_configured_planner_gives_a_free_path(algorithm: str) -> None:
    pl = make(0.3, algorithm=algorithm, time_limit_s=0.2)
    pl.set_base_map(base_map(pl), [COFFEE])
    r = pl.plan((1.0, 0.6), (5.0, 2.4))
    _assert_free_path(pl, r)
    assert r.first_solution_time_s <= r.planning_time_s


def test_replans_when_a_new_object_blocks_the_path() -> None:
    pl = make(0.5)
    pl.set_map(base_map(pl))
    first = pl.plan((1.0, 1.5), (5.0, 1.5))
    _assert_free_path(pl, first)
    same, replanned = pl.replan((1.0, 1.5), (5.0, 1.5), first)
    assert not replanned and same is first
    chair = ObjectFootprint(3, "chair", rect(2.8, 1.2, 3.3, 1.8), 0.0, 0.9)
    window = pl.set_base_map(base_map(pl), [chair]) or True
    assert window
    assert not pl.path_still_valid(first.path_xy_m)
    new, replanned = pl.replan((1.0, 1.5), (5.0, 1.5), first)
    assert replanned
    _assert_free_path(pl, new)
    assert new.map_version > first.map_version


def test_goal_change_triggers_replan() -> None:
    pl = make(0.5)
    pl.set_map(base_map(pl))
    first = pl.plan((1.0, 1.5), (5.0, 1.5))
    new, replanned = pl.replan((1.0, 1.5), (5.0, 2.2), first)
    assert replanned and new.ok and new.goal_xy_m == (5.0, 2.2)


def test_remaining_path_starts_at_projection() -> None:
    path = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0]])
    rem = remaining_path(path, np.array([3.0, 0.2]))
    np.testing.assert_allclose(rem, [[3.0, 0.0], [4.0, 0.0], [4.0, 4.0]])


def test_cost_weight_keeps_path_away_from_obstacles() -> None:
    near = make(0.3, cost_weight=0.0, refine_with_ompl=False)
    far = make(0.3, cost_weight=3.0, refine_with_ompl=False)
    for pl in (near, far):
        pl.set_base_map(base_map(pl), [COFFEE])
    a = near.plan((1.0, 1.2), (5.0, 1.2))
    b = far.plan((1.0, 1.2), (5.0, 1.2))
    ca = near.cspace.clearance_at(near.cspace.densify(a.path_xy_m)).min()
    cb = far.cspace.clearance_at(far.cspace.densify(b.path_xy_m)).min()
    assert cb > ca
    assert b.length_m >= a.length_m - 1e-9


def test_windowed_graph_update_equals_fresh_graph() -> None:
    from planner.gridsearch import GridGraph

    pl = make(0.5, refine_with_ompl=False)
    pl.set_map(base_map(pl))
    assert pl.plan((1.0, 1.4), (5.0, 1.6)).ok  # builds the full-resolution graph too
    assert set(pl._known.graphs) == {1, 2}
    chair = ObjectFootprint(3, "chair", rect(2.8, 1.2, 3.3, 1.8), 0.0, 0.9)
    pl.set_base_map(base_map(pl), [chair])
    for factor, graph in pl._known.graphs.items():
        fresh = GridGraph(pl.cspace, pl.config.cost_weight, factor)
        np.testing.assert_array_equal(graph.node_free, fresh.node_free)
        np.testing.assert_allclose(graph._weights, fresh._weights)


def test_snapped_plan_is_kept_for_the_same_requested_goal() -> None:
    pl = make(0.3, refine_with_ompl=False)
    pl.set_base_map(base_map(pl), [COFFEE])
    first = pl.plan((1.0, 1.5), (3.0, 1.5), snap_goal=True)
    assert first.ok and first.snapped_goal and first.requested_goal_xy_m == (3.0, 1.5)
    kept, replanned = pl.replan((1.0, 1.5), (3.0, 1.5), first)
    assert not replanned and kept is first
    _, replanned = pl.replan((1.0, 1.5), (4.5, 2.5), first)
    assert replanned


def test_px4_sitl_seed1_cabinet_graze_default_plans_keep_a_tracking_margin_from_occupancy() -> None:
    # A cabinet held only as occupancy (no class, no margin) beside the straight line: with
    # the default settings the path must pass it with more than the vehicle radius to spare,
    # because PX4 flies a few centimetres off its setpoints.
    cfg = PlannerConfig(flight_altitude_m=0.6, time_limit_s=0.15)
    assert cfg.tracking_margin_m >= 0.05
    pl = Planner(cfg)
    cm = base_map(pl)
    cost = cm.cost.copy()
    cost[:30, 56:64] = LETHAL_OBSTACLE  # x 2.8..3.2 m, y 0..1.5 m: the cabinet
    pl.set_base_map(Costmap(SPEC, cost, pl.band), [])
    r = pl.plan((1.0, 1.6), (5.0, 1.6))
    _assert_free_path(pl, r)
    pts = pl.cspace.densify(r.path_xy_m)
    dx = np.maximum(np.maximum(2.8 - pts[:, 0], pts[:, 0] - 3.2), 0.0)
    dy = np.maximum(pts[:, 1] - 1.5, 0.0)
    gap_m = np.hypot(dx, dy)
    assert gap_m.min() >= cfg.vehicle_radius_m + cfg.tracking_margin_m
