"""Unknown space: paths keep off unknown cells when a mapped route exists, and cross them
only when none does."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from planner.config import PlannerConfig
from planner.planner import Planner
from planner.types import PlanStatus
from semmap.costmap import FREE_SPACE, LETHAL_OBSTACLE, NO_INFORMATION, Costmap, VerticalBand
from semmap.grid import GridSpec

DATA = Path(__file__).resolve().parents[1] / "data"


def _densify(path_xy_m: np.ndarray, step_m: float = 0.01) -> np.ndarray:
    out = [np.linspace(a, b, int(np.ceil(np.linalg.norm(b - a) / step_m)) + 1)
           for a, b in zip(path_xy_m[:-1], path_xy_m[1:], strict=True)]
    return np.concatenate(out)


def _box_distance_m(points_xy_m: np.ndarray, center_xy_m: np.ndarray, size_m: np.ndarray,
                    yaw_rad: float) -> np.ndarray:
    """Distance of each point to a rotated rectangle (0 inside)."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    d = points_xy_m - center_xy_m
    a, b = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
    return np.hypot(np.maximum(np.abs(a) - size_m[0] / 2, 0.0), np.maximum(np.abs(b) - size_m[1] / 2, 0.0))


def _cabinet_case() -> tuple[Costmap, dict[str, np.ndarray]]:
    """The service's costmap (perception replayed on the flight's true track) when the vehicle
    re-planned after the SLAM loss in the GPS-denied PX4 SITL flight of seed 1: a 2 m cabinet
    seen only on the faces towards the vehicle, its far side unknown."""
    d = dict(np.load(DATA / "gd_seed1_cabinet_costmap.npz"))
    cost = d["cost"].astype(np.uint8)
    spec = GridSpec(float(d["resolution_m"]), (float(d["origin_xy_m"][0]), float(d["origin_xy_m"][1])), cost.shape)
    return Costmap(spec, cost, VerticalBand(float(d["band_m"][0]), float(d["band_m"][1]))), d


@pytest.mark.parametrize("prefer_known", [True, False])
def test_px4_gps_denied_seed1_replan_keeps_off_the_cabinets_unseen_side(prefer_known: bool) -> None:
    costmap, d = _cabinet_case()
    cfg = PlannerConfig(refine_with_ompl=False, prefer_known_space=prefer_known)
    pl = Planner(cfg)
    pl.set_map(costmap)
    res = pl.plan(d["start_xy_m"], d["goal_xy_m"])
    assert res.ok, res.reason
    gap = _box_distance_m(_densify(res.path_xy_m), d["cabinet_center_xy_m"], d["cabinet_size_m"],
                          float(d["cabinet_yaw_rad"])).min()
    if prefer_known:
        assert not res.through_unknown
        assert gap >= cfg.vehicle_radius_m, f"the path passes {gap:.3f} m from the cabinet"
    else:
        # Unknown cells at a small cost: the path runs along the unseen side, into the cabinet.
        assert gap < cfg.vehicle_radius_m


SPEC = GridSpec(0.05, (0.0, 0.0), (60, 120))  # 6 m (x) by 3 m (y)


def _walled(cost_fill: int = FREE_SPACE) -> np.ndarray:
    cost = np.full(SPEC.shape_rc, cost_fill, dtype=np.uint8)
    cost[0, :] = cost[-1, :] = LETHAL_OBSTACLE
    cost[:, 0] = cost[:, -1] = LETHAL_OBSTACLE
    return cost


def _planner(**kw: object) -> Planner:
    return Planner(PlannerConfig(vehicle_radius_m=0.2, time_limit_s=0.15, refine_with_ompl=False, **kw))  # type: ignore[arg-type]


def test_detour_through_mapped_space_beats_a_shortcut_through_unknown() -> None:
    pl = _planner()
    cost = _walled()
    cost[20:60, 55:65] = NO_INFORMATION  # an unseen block from y = 1 m to the far wall
    pl.set_map(Costmap(SPEC, cost, pl.band))
    res = pl.plan((1.0, 2.0), (5.0, 2.0))
    assert res.ok and not res.through_unknown
    # Around the block's open end, keeping the vehicle's radius off unknown cells.
    assert res.path_xy_m[:, 1].min() <= 1.0 - 0.2 + 1e-6


def test_only_route_through_unknown_is_planned_and_stays_valid() -> None:
    pl = _planner()
    cost = _walled()
    cost[:, 55:65] = NO_INFORMATION  # unseen from wall to wall
    cost[0, :] = cost[-1, :] = LETHAL_OBSTACLE
    pl.set_map(Costmap(SPEC, cost, pl.band))
    res = pl.plan((1.0, 1.5), (5.0, 1.5))
    assert res.ok and res.through_unknown and res.source.endswith("+unknown")
    # The path's checks use the space it was planned in: no re-plan on every map update.
    assert pl.path_still_valid(res.path_xy_m)
    cost[25:35, 55:65] = LETHAL_OBSTACLE  # a wall appears across it
    cost[:, 58:62] = LETHAL_OBSTACLE
    pl.set_map(Costmap(SPEC, cost, pl.band))
    assert not pl.path_still_valid(res.path_xy_m)


def test_start_next_to_unknown_cells_still_plans() -> None:
    pl = _planner()
    cost = _walled()
    cost[20:40, 5:25] = NO_INFORMATION
    cost[28:32, 13:17] = FREE_SPACE  # the vehicle sits in a small seen patch
    pl.set_map(Costmap(SPEC, cost, pl.band))
    res = pl.plan((0.75, 1.5), (5.0, 1.5))
    assert res.ok and res.through_unknown


def test_forbidden_unknown_space_has_no_fallback() -> None:
    pl = _planner(unknown_cost=1.0)
    cost = _walled()
    cost[:, 55:65] = NO_INFORMATION
    pl.set_map(Costmap(SPEC, cost, pl.band))
    res = pl.plan((1.0, 1.5), (5.0, 1.5))
    assert res.status is PlanStatus.DISCONNECTED
