"""OMPL geometric planning over a :class:`~planner.cspace.CSpace`.

The state space is the plane (``RealVectorStateSpace(2)``, map frame, metres). Every callback
OMPL makes into Python is one array lookup or one vectorised numpy call:

* state validity: one index into the precomputed free grid;
* motion validity (:class:`GridMotionValidator`): the whole segment sampled every half cell
  in one call, not one Python call per step;
* objective (:class:`MapCostObjective`): path length plus ``weight`` times the integral of the
  cell cost, integrated per motion with the trapezoid rule on its end states (as OMPL's
  ``StateCostIntegralObjective`` does), with the Euclidean distance as admissible heuristic.

When an upper bound on the optimal cost is known (the grid seed's cost), the sampling bounds
shrink to the bounding box of the informed ellipse (every path cheaper than the bound lies in
it, since the cost is never below the length), and the objective's threshold is set to the
bound so the planner returns as soon as it beats the seed.

``solve`` holds the GIL for its whole duration; :mod:`planner.worker` runs it in a separate
process so a service never stalls.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray
from ompl import base as ob
from ompl import geometric as og
from ompl import util as ou

from planner.cspace import CSpace
from semmap.errors import PlanningError

log = logging.getLogger(__name__)

#: Config name -> OMPL planner class name. Only single-threaded planners: a planner that calls
#: the Python checkers from a thread of its own (PRM, PRM*) deadlocks on the GIL.
PLANNERS: dict[str, str] = {
    "rrtstar": "RRTstar",
    "informed_rrtstar": "InformedRRTstar",
    "bitstar": "BITstar",
    "rrtconnect": "RRTConnect",
}


def set_ompl_seed(seed: int) -> None:
    """Seed OMPL's global random generator (call before the first planner is created)."""
    ou.RNG.setSeed(int(seed))


class GridMotionValidator(ob.MotionValidator):  # type: ignore[misc]
    """Checks a whole segment against the free grid in one vectorised call."""

    def __init__(self, si: Any, cs: CSpace) -> None:
        super().__init__(si)
        self._cs = cs

    def checkMotion(self, s1: Any, s2: Any, *last_valid: Any) -> bool:  # noqa: N802 - OMPL API
        return self._cs.segment_free((s1[0], s1[1]), (s2[0], s2[1]))


class MapCostObjective(ob.OptimizationObjective):  # type: ignore[misc]
    """Length + weight * integral of the map cost (trapezoid on each motion's end states)."""

    def __init__(self, si: Any, cs: CSpace, weight: float) -> None:
        super().__init__(si)
        self._cost = cs.cost.ravel()
        self._ox, self._oy = cs.spec.origin_xy_m
        self._res = cs.spec.resolution_m
        self._rows, self._cols = cs.spec.shape_rc
        self._w = float(weight)

    def _cell_cost(self, x: float, y: float) -> float:
        c = int((x - self._ox) / self._res)
        r = int((y - self._oy) / self._res)
        if 0 <= r < self._rows and 0 <= c < self._cols:
            return float(self._cost[r * self._cols + c])
        return 1.0

    def stateCost(self, s: Any) -> Any:  # noqa: N802 - OMPL API
        return ob.Cost(1.0 + self._w * self._cell_cost(s[0], s[1]))

    def motionCost(self, s1: Any, s2: Any) -> Any:  # noqa: N802 - OMPL API
        x1, y1, x2, y2 = s1[0], s1[1], s2[0], s2[1]
        length = math.hypot(x2 - x1, y2 - y1)
        c = 0.5 * (self._cell_cost(x1, y1) + self._cell_cost(x2, y2))
        return ob.Cost(length * (1.0 + self._w * c))

    def motionCostHeuristic(self, s1: Any, s2: Any) -> Any:  # noqa: N802 - OMPL API
        return ob.Cost(math.hypot(s2[0] - s1[0], s2[1] - s1[1]))


def informed_bounds(
    cs: CSpace, start_xy_m: NDArray[np.floating], goal_xy_m: NDArray[np.floating],
    cost_bound: float | None,
) -> tuple[float, float, float, float]:
    """Sampling box (x0, y0, x1, y1): the map, cut to the informed ellipse's bounding box.

    The ellipse has the start and goal as foci and ``cost_bound`` as major axis: it holds
    every path whose length, hence whose cost, is below the bound.
    """
    x0, y0, x1, y1 = cs.spec.extent_xy_m
    if cost_bound is None or not math.isfinite(cost_bound):
        return x0, y0, x1, y1
    s = np.asarray(start_xy_m, dtype=np.float64).reshape(2)
    g = np.asarray(goal_xy_m, dtype=np.float64).reshape(2)
    c = 0.5 * (s + g)
    d = g - s
    f = 0.5 * float(np.hypot(*d))
    a = 0.5 * max(cost_bound, 2.0 * f)
    b = math.sqrt(max(a * a - f * f, 0.0))
    th = math.atan2(d[1], d[0])
    hx = math.sqrt((a * math.cos(th)) ** 2 + (b * math.sin(th)) ** 2)
    hy = math.sqrt((a * math.sin(th)) ** 2 + (b * math.cos(th)) ** 2)
    return max(x0, c[0] - hx), max(y0, c[1] - hy), min(x1, c[0] + hx), min(y1, c[1] + hy)


def _to_array(path: Any) -> NDArray[np.float64]:
    n = path.getStateCount()
    return np.array([[path.getState(i)[0], path.getState(i)[1]] for i in range(n)], dtype=np.float64)


def _grid_space(cs: CSpace, box: tuple[float, float, float, float]) -> tuple[Any, Any, GridMotionValidator]:
    """The 2D state space over ``box`` (x0, y0, x1, y1) and its space information, states
    and motions checked against the free grid; and the motion validator (keep it alive)."""
    x0, y0, x1, y1 = box
    space = ob.RealVectorStateSpace(2)
    bounds = ob.RealVectorBounds(2)
    bounds.setLow(0, x0)
    bounds.setHigh(0, x1)
    bounds.setLow(1, y0)
    bounds.setHigh(1, y1)
    space.setBounds(bounds)
    si = ob.SpaceInformation(space)
    free = cs.free.ravel()
    ox, oy = cs.spec.origin_xy_m
    res = cs.spec.resolution_m
    rows, cols = cs.spec.shape_rc

    def valid(s: Any) -> bool:
        c = int((s[0] - ox) / res)
        r = int((s[1] - oy) / res)
        return 0 <= r < rows and 0 <= c < cols and bool(free[r * cols + c])

    si.setStateValidityChecker(valid)
    validator = GridMotionValidator(si, cs)
    si.setMotionValidator(validator)
    si.setup()
    return space, si, validator


def _objective(si: Any, cs: CSpace, cost_weight: float, cost_bound: float | None) -> Any:
    """Length + map cost (plain length at weight 0), satisfied below a finite ``cost_bound``."""
    objective: Any
    if cost_weight > 0.0:
        objective = MapCostObjective(si, cs, cost_weight)
    else:
        objective = ob.PathLengthOptimizationObjective(si)
    if cost_bound is not None and math.isfinite(cost_bound):
        objective.setCostThreshold(ob.Cost(float(cost_bound)))
    return objective


def ompl_solve(
    cs: CSpace,
    start_xy_m: NDArray[np.floating],
    goal_xy_m: NDArray[np.floating],
    algorithm: str,
    time_limit_s: float,
    cost_weight: float,
    cost_bound: float | None = None,
    simplify: bool = True,
) -> NDArray[np.float64] | None:
    """Plan start -> goal with an OMPL planner; the (K, 2) path, or None if none was found.

    ``algorithm``: a key of :data:`PLANNERS`. ``time_limit_s``: the planner's budget.
    ``cost_bound``: a known solution's objective (restricts sampling, sets the threshold).
    ``simplify``: run OMPL's ``PathSimplifier`` (shortcuts, vertex reduction) on the result.
    Start and goal must be free; the returned path is validated by the motion validator.
    """
    if algorithm not in PLANNERS:
        raise PlanningError(f"unknown planner {algorithm!r}; choose one of {sorted(PLANNERS)}")
    if time_limit_s <= 0.0:
        return None
    ou.setLogLevel(ou.LOG_ERROR)
    box = informed_bounds(cs, start_xy_m, goal_xy_m, cost_bound)
    if box[2] - box[0] <= cs.spec.resolution_m or box[3] - box[1] <= cs.spec.resolution_m:
        return None
    # The validator stays referenced until the solve ends: OMPL calls back into it.
    space, si, validator = _grid_space(cs, box)
    start = space.allocState()
    goal = space.allocState()
    start[0], start[1] = float(start_xy_m[0]), float(start_xy_m[1])
    goal[0], goal[1] = float(goal_xy_m[0]), float(goal_xy_m[1])
    if not (space.satisfiesBounds(start) and space.satisfiesBounds(goal)):
        return None
    pdef = ob.ProblemDefinition(si)
    pdef.setStartAndGoalStates(start, goal)
    objective = _objective(si, cs, cost_weight, cost_bound)
    pdef.setOptimizationObjective(objective)
    planner = getattr(og, PLANNERS[algorithm])(si)
    planner.setProblemDefinition(pdef)
    planner.setup()
    planner.solve(float(time_limit_s))
    if not pdef.hasExactSolution():
        return None
    path = pdef.getSolutionPath()
    if simplify and path.getStateCount() > 2:
        og.PathSimplifier(si).simplifyMax(path)
    out = _to_array(path)
    if not cs.path_free(out):
        log.warning("OMPL %s returned a path that fails the dense check; discarded", algorithm)
        return None
    return out
