"""The planner: costmap in, checked path (or a reason there is none) out. Pure computation.

One :class:`Planner` keeps the precomputed fields of the latest map version (configuration
space, search graphs) and answers requests against them:

1. input checks: start/goal inside the map (and geofence) and free for the vehicle's radius,
   else ``*_OUTSIDE_MAP`` / ``*_BLOCKED``; with ``snap_goal`` a bad goal moves to the nearest
   free point reachable from the start instead;
2. first path: Dijkstra on the (coarse, then if needed full-resolution) grid graph; an
   infinite distance is a proof of ``DISCONNECTED`` at the grid's resolution;
3. any-angle post-processing of that path (cost-aware shortcuts, corner sliding);
4. OMPL (the configured planner, with the length + map-cost objective) for the rest of the
   time budget, sampling only the informed box of the best cost so far; its path replaces
   the first one only if its objective is lower.

Every returned path is checked densely (half-cell samples) against the clearance field.
Map changes go through :meth:`Planner.set_map`, which updates only the window that changed;
:meth:`Planner.path_still_valid` tells a caller when the remaining path must be replanned.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from planner.config import PlannerConfig
from planner.cspace import CSpace, build_cspace, update_cspace
from planner.gridsearch import GridGraph, refine_vertices, shortcut
from planner.ompl_backend import ompl_solve
from planner.types import PlanResult, PlanStatus, path_length_m
from semmap.costmap import NO_INFORMATION, Costmap, ObjectFootprint, VerticalBand
from semmap.errors import PlanningError
from semmap.grid import Bounds
from semmap.inflation import InflationParams
from semmap.layers import paint_objects

log = logging.getLogger(__name__)

#: Failures no other treatment of unknown cells can change.
_OUTSIDE = (PlanStatus.START_OUTSIDE_MAP, PlanStatus.GOAL_OUTSIDE_MAP)


def _xy(value: Sequence[float] | NDArray[np.floating], name: str) -> NDArray[np.float64]:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.shape != (2,) or not np.all(np.isfinite(arr)):
        raise PlanningError(f"{name} must be two finite numbers (x, y) in metres, got {value!r}")
    return arr


class _Fields:
    """One configuration space and its search graphs, kept up to date with the map."""

    def __init__(self, params: InflationParams, cost_weight: float) -> None:
        self.params = params
        self.cost_weight = cost_weight
        self.cs: CSpace | None = None
        self.graphs: dict[int, GridGraph] = {}

    def update(self, costmap: Costmap, version: int) -> Bounds | None:
        """Adopt ``costmap``; returns the window whose fields changed (None: none). The first
        map (or one with a new grid geometry or band) is precomputed in full, later ones by
        window."""
        if self.cs is None or self.cs.spec != costmap.spec or self.cs.band != costmap.band:
            self.cs = build_cspace(costmap, self.params, version)
            self.graphs = {}
            return costmap.spec.bounds
        self.cs, window = update_cspace(self.cs, costmap, version)
        for g in self.graphs.values():
            g.update(self.cs, window)
        return window

    def graph(self, factor: int) -> GridGraph:
        assert self.cs is not None
        g = self.graphs.get(factor)
        if g is None:
            g = GridGraph(self.cs, self.cost_weight, factor)
            self.graphs[factor] = g
        return g


class Planner:
    """Plans paths for a multicopter at the configured altitude on the latest costmap.

    With ``prefer_known_space`` it keeps two configuration spaces: one in which unknown cells
    block like obstacles (used first) and, built on the first request that needs it, one in
    which they cost ``unknown_cost``.
    """

    def __init__(self, config: PlannerConfig) -> None:
        self.config = config
        self.params = InflationParams(
            vehicle_radius_m=config.vehicle_radius_m,
            tracking_margin_m=config.tracking_margin_m,
            unknown_cost=config.unknown_cost,
            geofence_xy_m=config.geofence_xy_m,
        )
        strict = config.prefer_known_space and config.unknown_cost < 1.0
        known_params = dataclasses.replace(self.params, unknown_cost=1.0) if strict else self.params
        self._known = _Fields(known_params, config.cost_weight)
        #: The space with unknown cells traversable, once a request needed it (None: not yet
        #: or never: unknown cells are forbidden or not avoided first).
        self._any: _Fields | None = None
        self._fallback = strict
        #: The fields the current request works on.
        self._active = self._known
        self._costmap: Costmap | None = None
        #: The current map holds unknown cells (without any, the fallback could change nothing).
        self._has_unknown = False
        self._version = 0
        #: Seconds spent preparing the fields of the last map version.
        self.last_prepare_s = 0.0

    # --- the map --------------------------------------------------------------------

    @property
    def band(self) -> VerticalBand:
        """The vehicle's vertical band at the configured flight altitude."""
        return self.config.band_at()

    @property
    def cspace(self) -> CSpace:
        if self._active.cs is None:
            raise PlanningError("no map yet: call set_map() before planning")
        return self._active.cs

    @property
    def map_version(self) -> int:
        return self._version

    def set_base_map(self, base: Costmap, objects: Sequence[ObjectFootprint],
                     version: int | None = None, min_existence: float = 0.0,
                     class_margins_m: Mapping[str, float] | None = None) -> None:
        """Use an occupancy costmap plus object footprints, costed by the map's layers at the
        vehicle's band: objects at or above ``min_existence`` are lethal with their margin
        (their class's from ``class_margins_m`` where they have none)."""
        self.set_map(paint_objects(base, objects, self.band, existence_confirm=min_existence,
                                   class_margins_m=class_margins_m), version)

    def set_map(self, costmap: Costmap, version: int | None = None) -> Bounds | None:
        """Adopt a new costmap version; returns the window whose fields changed.

        The first map (or one with a new grid geometry or band) is precomputed in full; later
        versions only recompute the window that changed.
        """
        t0 = time.perf_counter()
        self._version = self._version + 1 if version is None else int(version)
        self._costmap = costmap
        self._has_unknown = bool(np.any(costmap.cost == NO_INFORMATION))
        window = self._known.update(costmap, self._version)
        if self._any is not None:
            other = self._any.update(costmap, self._version)
            window = other if window is None else window if other is None else window.union(other)
        # The coarse graph gives first paths; the full-resolution one is built on first use
        # (after the first path exists) and from then on kept up to date by windowed updates.
        self._known.graph(self._coarse_factor())
        self.last_prepare_s = time.perf_counter() - t0
        return window

    def _unknown_fields(self) -> _Fields:
        """The space with unknown cells traversable, built from the current map on first use."""
        if self._any is None:
            if self._costmap is None:
                raise PlanningError("no map yet: call set_map() before planning")
            self._any = _Fields(self.params, self.config.cost_weight)
            self._any.update(self._costmap, self._version)
        return self._any

    def _coarse_factor(self) -> int:
        return max(1, int(round(self.config.search_cell_m / self.cspace.spec.resolution_m)))

    def _graph(self, factor: int) -> GridGraph:
        if self._active.cs is None:
            raise PlanningError("no map yet: call set_map() before planning")
        return self._active.graph(factor)

    # --- checks ---------------------------------------------------------------------

    def path_still_valid(self, path_xy_m: NDArray[np.floating]) -> bool:
        """True if the (K, 2) polyline is still free on the current map: in the space it may
        have been planned in (through unknown cells, once a request needed that)."""
        fields = self._any or self._known
        if fields.cs is None:
            raise PlanningError("no map yet: call set_map() before planning")
        return fields.cs.path_free(path_xy_m)

    def escape_point(self, xy_m: NDArray[np.floating], extra_m: float = 0.05) -> NDArray[np.float64] | None:
        """The nearest point to ``xy_m`` where the vehicle fits with ``extra_m`` to spare on
        the current map (see :meth:`CSpace.escape_point`), off unknown cells where possible."""
        point = self.cspace.escape_point(xy_m, extra_m)
        if point is None and self._fallback:
            point = self._unknown_fields().cs.escape_point(xy_m, extra_m)  # type: ignore[union-attr]
        return point

    def _inside(self, xy: NDArray[np.float64]) -> bool:
        if not bool(self.cspace.spec.contains_xy(xy.reshape(1, 2))[0]):
            return False
        fence = self.config.geofence_xy_m
        return fence is None or (fence[0] <= xy[0] <= fence[2] and fence[1] <= xy[1] <= fence[3])

    # --- planning -------------------------------------------------------------------

    def plan(
        self,
        start_xy_m: Sequence[float] | NDArray[np.floating],
        goal_xy_m: Sequence[float] | NDArray[np.floating],
        time_limit_s: float | None = None,
        snap_goal: bool | None = None,
        refine: bool | None = None,
    ) -> PlanResult:
        """Plan from ``start_xy_m`` to ``goal_xy_m`` (map frame, metres) on the current map.

        ``time_limit_s`` (default: config) bounds the whole request; the first path usually
        takes a small part of it and OMPL improves on it in the rest. ``snap_goal`` (default:
        config) moves a goal outside the map, blocked or unreachable to the nearest reachable
        free point. ``refine`` (default: config) enables the OMPL stage. Never raises for
        "no path": the result's status and reason say why.

        With ``prefer_known_space`` the path keeps off unknown cells when it can; only when
        that fails for another reason than a start or goal outside the map is it planned
        through them, for what is left of the budget.
        """
        t0 = time.perf_counter()
        budget = self.config.time_limit_s if time_limit_s is None else float(time_limit_s)
        self._active = self._known
        known = self._plan(start_xy_m, goal_xy_m, budget, snap_goal, refine)
        if known.ok or not self._fallback or not self._has_unknown or known.status in _OUTSIDE:
            return known
        self._active = self._unknown_fields()
        try:
            res = self._plan(start_xy_m, goal_xy_m, max(0.0, budget - (time.perf_counter() - t0)),
                             snap_goal, refine)
        finally:
            self._active = self._known
        if not res.ok:
            return res
        log.info("no path through mapped free space (%s); planned through unknown cells", known.reason)
        return dataclasses.replace(res, planning_time_s=time.perf_counter() - t0, through_unknown=True,
                                   source=res.source + "+unknown")

    def _plan(
        self,
        start_xy_m: Sequence[float] | NDArray[np.floating],
        goal_xy_m: Sequence[float] | NDArray[np.floating],
        time_limit_s: float | None,
        snap_goal: bool | None,
        refine: bool | None,
    ) -> PlanResult:
        """:meth:`plan` in the active fields."""
        t0 = time.perf_counter()
        budget, snap, use_ompl = self._request_options(time_limit_s, snap_goal, refine)
        start = _xy(start_xy_m, "start")
        goal = _xy(goal_xy_m, "goal")
        requested = (float(goal[0]), float(goal[1]))
        version = self._version

        goal, snapped, problem = self._usable_endpoints(start, goal, snap)
        if problem is not None:
            return self._failure(problem, t0, version)

        t_search = time.perf_counter()
        first = self._first_path(start, goal)
        if first is None:
            if snap and not snapped:
                res = self._plan_to_snapped_goal(start, goal, budget, t0, refine, requested)
                if res is not None:
                    return res
            return self._failure(self._disconnected_problem(start, goal), t0, version)
        path, used_factor = first
        t_first = time.perf_counter()
        best, best_cost, source = self._polished_best(path, used_factor, start, goal, budget, t0)
        t_smooth = time.perf_counter()
        ompl_improved = 0.0
        remaining = budget - (t_smooth - t0)
        if use_ompl and remaining > 0.01:
            better = self._ompl_improvement(start, goal, remaining, best_cost)
            if better is not None:
                best, best_cost = better
                source, ompl_improved = f"ompl:{self.config.algorithm}", 1.0
        t_end = time.perf_counter()
        return PlanResult(
            status=PlanStatus.OK,
            reason="goal snapped to the nearest reachable free point" if snapped else "ok",
            path_xy_m=best, length_m=path_length_m(best), cost=best_cost,
            planning_time_s=t_end - t0, first_solution_time_s=t_first - t0,
            goal_xy_m=(float(goal[0]), float(goal[1])), snapped_goal=snapped, source=source,
            requested_goal_xy_m=requested, map_version=version,
            stats={
                "search_s": t_first - t_search, "smooth_s": t_smooth - t_first,
                "ompl_s": t_end - t_smooth, "ompl_improved": ompl_improved,
                "first_length_m": path_length_m(path),
            },
        )

    def _request_options(self, time_limit_s: float | None, snap_goal: bool | None,
                         refine: bool | None) -> tuple[float, bool, bool]:
        """(budget_s, snap, use_ompl): the request's options, the config's where they are None."""
        cfg = self.config
        budget = cfg.time_limit_s if time_limit_s is None else float(time_limit_s)
        snap = cfg.snap_goal_to_free if snap_goal is None else bool(snap_goal)
        use_ompl = cfg.refine_with_ompl if refine is None else bool(refine)
        return budget, snap, use_ompl

    def _failure(self, problem: tuple[PlanStatus, str], t0: float, version: int) -> PlanResult:
        """The failure result for ``problem`` (status, reason), logged, timed from ``t0``."""
        status, reason = problem
        log.info("no path (%s): %s", status.value, reason)
        return PlanResult.failure(status, reason, time.perf_counter() - t0, version)

    def _start_problem(self, start: NDArray[np.float64]) -> tuple[PlanStatus, str] | None:
        """Why the vehicle cannot start at ``start`` (status, reason), or None if it can."""
        if not self._inside(start):
            return (PlanStatus.START_OUTSIDE_MAP,
                    f"start ({start[0]:.2f}, {start[1]:.2f}) m is outside the map/geofence {self._extent_text()}")
        return self._blocked_problem(start, "start", PlanStatus.START_BLOCKED)

    def _goal_problem(self, goal: NDArray[np.float64]) -> tuple[PlanStatus, str] | None:
        """Why the vehicle cannot stop at ``goal`` (status, reason), or None if it can."""
        if not self._inside(goal):
            return (PlanStatus.GOAL_OUTSIDE_MAP,
                    f"goal ({goal[0]:.2f}, {goal[1]:.2f}) m is outside the map/geofence {self._extent_text()}")
        return self._blocked_problem(goal, "goal", PlanStatus.GOAL_BLOCKED)

    def _usable_endpoints(
        self, start: NDArray[np.float64], goal: NDArray[np.float64], snap: bool,
    ) -> tuple[NDArray[np.float64], bool, tuple[PlanStatus, str] | None]:
        """(goal, snapped, failure): ``goal`` itself when the vehicle can start at ``start`` and
        stop there, else with ``snap`` the nearest free point reachable from ``start``; failure
        (status, reason) when the start is not usable or neither goal is possible."""
        start_problem = self._start_problem(start)
        if start_problem is not None:
            return goal, False, start_problem
        goal_problem = self._goal_problem(goal)
        if goal_problem is None:
            return goal, False, None
        if not snap:
            return goal, False, goal_problem
        new_goal = self._snap(start, goal)
        if new_goal is None:
            return goal, False, (goal_problem[0], goal_problem[1] + "; no reachable free point to snap to")
        log.info("goal (%.2f, %.2f) snapped to (%.2f, %.2f)", goal[0], goal[1], new_goal[0], new_goal[1])
        return new_goal, True, None

    def _blocked_problem(self, xy: NDArray[np.float64], name: str,
                         status: PlanStatus) -> tuple[PlanStatus, str] | None:
        cs = self.cspace
        if bool(cs.is_free(xy.reshape(1, 2))[0]):
            return None
        clr = float(cs.clearance_at(xy.reshape(1, 2))[0])
        # The clearance field already has the class and tracking margins taken off.
        return (status, f"{name} ({xy[0]:.2f}, {xy[1]:.2f}) m is blocked: clearance beyond the margins "
                        f"{clr:.2f} m < vehicle radius {self.config.vehicle_radius_m:.2f} m")

    def _disconnected_problem(self, start: NDArray[np.float64],
                              goal: NDArray[np.float64]) -> tuple[PlanStatus, str]:
        """(DISCONNECTED, reason) for a start and goal the grid proves in separate free regions."""
        cfg = self.config
        return (PlanStatus.DISCONNECTED,
                f"no free path from ({start[0]:.2f}, {start[1]:.2f}) to ({goal[0]:.2f}, {goal[1]:.2f}) m "
                f"for a vehicle of radius {cfg.vehicle_radius_m:.2f} m (+ tracking margin {cfg.tracking_margin_m:.2f} m) "
                f"at {cfg.flight_altitude_m:.2f} m "
                "altitude: they are in separate free regions")

    def _first_path(self, start: NDArray[np.float64],
                    goal: NDArray[np.float64]) -> tuple[NDArray[np.float64], int] | None:
        """The first free grid path and the graph factor that gave it: coarse, then full
        resolution; None when the grid proves start and goal disconnected."""
        for f in sorted({self._coarse_factor(), 1}, reverse=True):
            outcome = self._graph(f).search(start, goal)
            if outcome.path_xy_m is not None and self.cspace.path_free(outcome.path_xy_m):
                return outcome.path_xy_m, f
        return None

    def _plan_to_snapped_goal(self, start: NDArray[np.float64], goal: NDArray[np.float64], budget: float,
                              t0: float, refine: bool | None,
                              requested: tuple[float, float]) -> PlanResult | None:
        """Plan to the nearest free point reachable from ``start`` for an unreachable goal
        with the rest of the budget; None when there is no such point apart from ``goal``."""
        new_goal = self._snap(start, goal)
        if new_goal is None or float(np.linalg.norm(new_goal - goal)) <= 1e-9:
            return None
        res = self._plan(start, new_goal, max(0.0, budget - (time.perf_counter() - t0)),
                         snap_goal=False, refine=refine)
        if not res.ok:
            return res
        return dataclasses.replace(
            res, snapped_goal=True, planning_time_s=time.perf_counter() - t0,
            requested_goal_xy_m=requested,
            reason="goal unreachable; snapped to the nearest reachable free point",
        )

    def _polished_best(self, path: NDArray[np.float64], used_factor: int, start: NDArray[np.float64],
                       goal: NDArray[np.float64], budget: float,
                       t0: float) -> tuple[NDArray[np.float64], float, str]:
        """The polished first path, or the polished full-resolution one if it costs less:
        the coarse grid can close a narrow gap and force a detour. Returns (path, cost, source)."""
        cs, w = self.cspace, self.config.cost_weight
        best = self._polish(path)
        best_cost = cs.path_cost(best, w)
        source = f"grid:{used_factor}"
        if used_factor > 1 and budget - (time.perf_counter() - t0) > 0.0:
            fine = self._graph(1).search(start, goal).path_xy_m
            if fine is not None and cs.path_free(fine):
                fine = self._polish(fine)
                c = cs.path_cost(fine, w)
                if c < best_cost - 1e-9:
                    best, best_cost, source = fine, c, "grid:1"
        return best, best_cost, source

    def _ompl_improvement(self, start: NDArray[np.float64], goal: NDArray[np.float64], remaining_s: float,
                          best_cost: float) -> tuple[NDArray[np.float64], float] | None:
        """A polished, free OMPL path that costs less than ``best_cost`` (path, cost), or None."""
        cs, cfg = self.cspace, self.config
        cand = ompl_solve(cs, start, goal, cfg.algorithm, remaining_s, cfg.cost_weight, cost_bound=best_cost)
        if cand is None:
            return None
        cand = self._polish(cand)
        if not cs.path_free(cand):
            return None
        c = cs.path_cost(cand, cfg.cost_weight)
        return (cand, c) if c < best_cost - 1e-6 else None

    def replan(
        self,
        current_xy_m: Sequence[float] | NDArray[np.floating],
        goal_xy_m: Sequence[float] | NDArray[np.floating],
        previous: PlanResult | None,
        time_limit_s: float | None = None,
    ) -> tuple[PlanResult, bool]:
        """Keep ``previous`` while its remaining part is free and its goal unchanged, else plan.

        Returns (result, replanned). The remaining part starts at the path point nearest to
        ``current_xy_m``.
        """
        cur = _xy(current_xy_m, "current position")
        goal = _xy(goal_xy_m, "goal")
        if previous is not None and previous.ok and previous.requested_goal_xy_m is not None:
            same_goal = float(np.linalg.norm(np.array(previous.requested_goal_xy_m) - goal)) < 1e-6
            remaining = remaining_path(previous.path_xy_m, cur)
            if same_goal and self.path_still_valid(remaining):
                return previous, False
        return self.plan(cur, goal, time_limit_s), True

    def _polish(self, path: NDArray[np.float64]) -> NDArray[np.float64]:
        """Any-angle shortcuts and corner sliding of a free path (the input if that fails)."""
        cs, w = self.cspace, self.config.cost_weight
        out = refine_vertices(cs, shortcut(cs, path, w), w)
        return out if cs.path_free(out) else path

    def _snap(self, start: NDArray[np.float64], goal: NDArray[np.float64]) -> NDArray[np.float64] | None:
        """Nearest free point reachable from ``start`` (full-resolution graph) to ``goal``."""
        return self._graph(1).reachable_nearest(start, goal)

    def _extent_text(self) -> str:
        x0, y0, x1, y1 = self.cspace.spec.extent_xy_m
        fence = self.config.geofence_xy_m
        if fence is not None:
            x0, y0, x1, y1 = max(x0, fence[0]), max(y0, fence[1]), min(x1, fence[2]), min(y1, fence[3])
        return f"x [{x0:.2f}, {x1:.2f}] y [{y0:.2f}, {y1:.2f}] m"


def remaining_path(path_xy_m: NDArray[np.floating], current_xy_m: NDArray[np.floating]) -> NDArray[np.float64]:
    """The part of a (K, 2) polyline from the point nearest to ``current_xy_m`` onwards."""
    p = np.asarray(path_xy_m, dtype=np.float64).reshape(-1, 2)
    c = np.asarray(current_xy_m, dtype=np.float64).reshape(2)
    if len(p) < 2:
        return p.copy()
    a, b = p[:-1], p[1:]
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", c - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12), 0.0, 1.0)
    proj = a + t[:, None] * ab
    k = int(np.argmin(np.linalg.norm(proj - c, axis=1)))
    return np.vstack([proj[k:k + 1], p[k + 1:]])

