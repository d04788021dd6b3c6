"""Values that cross the planner's boundary: the request, the result and its status.

"No path" is a result (:class:`PlanStatus` other than ``OK``, with a reason a person can read),
never an exception: the vehicle holds instead of flying. :class:`semmap.errors.PlanningError`
is raised only for programming or input errors (wrong array shapes, NaN coordinates).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray


class PlanStatus(enum.Enum):
    """Outcome of one planning request."""

    OK = "ok"
    START_BLOCKED = "start_blocked"
    GOAL_BLOCKED = "goal_blocked"
    START_OUTSIDE_MAP = "start_outside_map"
    GOAL_OUTSIDE_MAP = "goal_outside_map"
    DISCONNECTED = "disconnected"
    TIMEOUT = "timeout"

    @property
    def ok(self) -> bool:
        return self is PlanStatus.OK


@dataclass(frozen=True, eq=False)
class PlanResult:
    """A planned path in the map frame, or the reason there is none.

    ``path_xy_m``: (K, 2) polyline from start to goal (K >= 2 when ``status`` is OK, else
    (0, 2)). ``length_m`` its length, ``cost`` its objective value (length plus the weighted
    integral of the map cost, metres). ``planning_time_s``: wall time of the whole request;
    ``first_solution_time_s``: time until the first valid path existed (NaN without one).
    ``goal_xy_m`` is the goal actually planned to (differs from ``requested_goal_xy_m`` when
    snapped).
    ``source`` names the stage that produced the final path (``grid``, ``ompl:<planner>``).
    ``through_unknown``: the path may cross unknown cells (no path kept off them).
    """

    status: PlanStatus
    reason: str
    path_xy_m: NDArray[np.float64]  # (K, 2)
    length_m: float
    cost: float
    planning_time_s: float
    first_solution_time_s: float
    goal_xy_m: tuple[float, float] | None = None
    snapped_goal: bool = False
    source: str = ""
    map_version: int = 0
    requested_goal_xy_m: tuple[float, float] | None = None
    stats: dict[str, float] = field(default_factory=dict)
    through_unknown: bool = False

    @property
    def ok(self) -> bool:
        return self.status is PlanStatus.OK

    @classmethod
    def failure(
        cls, status: PlanStatus, reason: str, planning_time_s: float, map_version: int = 0
    ) -> "PlanResult":
        """A result without a path (the vehicle should hold position)."""
        return cls(
            status=status, reason=reason, path_xy_m=np.zeros((0, 2)), length_m=float("nan"),
            cost=float("nan"), planning_time_s=planning_time_s,
            first_solution_time_s=float("nan"), map_version=map_version,
        )


def path_length_m(path_xy_m: NDArray[np.floating]) -> float:
    """Length in metres of a (K, 2) polyline (0 for fewer than two points)."""
    p = np.asarray(path_xy_m, dtype=np.float64).reshape(-1, 2)
    if len(p) < 2:
        return 0.0
    return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))
