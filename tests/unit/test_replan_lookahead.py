"""Where a re-plan in flight starts when the path ahead has become blocked
(:meth:`MissionRunner._check_ahead`), with a fake planning process and trajectory clock."""

from __future__ import annotations

import asyncio
import time
from typing import Any

import numpy as np

from companion.service.mission_runner import MIN_REPLAN_LOOKAHEAD_S, MissionRunner
from planner.config import PlannerConfig
from planner.trajectory import time_parametrize


class _SlowPlanning:
    """A planning process that answers the first check "blocked" only after the vehicle has
    flown on ``delay_s`` of trajectory time (it prepared the changed map first), and every
    later check "free" at once."""

    def __init__(self, clock: list[float], delay_s: float) -> None:
        self.clock, self.delay_s, self.calls = clock, delay_s, 0

    def path_free(self, costmap: Any, version: int, path_xy_m: Any) -> bool:
        self.calls += 1
        if self.calls == 1:
            self.clock[0] += self.delay_s
            return False
        return True


def test_a_slow_first_answer_starts_the_replan_ahead_of_where_the_vehicle_is_by_then() -> None:
    # A CI run on a loaded machine: the check came back after the vehicle had passed the point
    # it proposed to re-plan from, and the vehicle stopped mid-leg instead of flying on.
    cfg = PlannerConfig()
    runner = MissionRunner(None, None, lambda: None, cfg)  # type: ignore[arg-type]
    traj = time_parametrize(np.array([[0.0, 0.0], [8.0, 0.0]]), 1.0, runner.limits)
    clock = [2.0]
    runner.planning = _SlowPlanning(clock, delay_s=1.5)  # type: ignore[assignment]
    runner._version_of = lambda costmap: 1  # type: ignore[method-assign]

    free, t_start = asyncio.run(runner._check_ahead(traj, lambda: clock[0]))

    assert not free and t_start is not None
    assert t_start >= clock[0] + 0.5 * MIN_REPLAN_LOOKAHEAD_S, (t_start, clock[0])


class _LoadedPlanning:
    """A planning process that takes ``wall_s`` of wall time for the first check (a loaded
    CPU), during which the vehicle flies no trajectory time, and answers "free" after."""

    def __init__(self, wall_s: float) -> None:
        self.wall_s, self.calls = wall_s, 0

    def path_free(self, costmap: Any, version: int, path_xy_m: Any) -> bool:
        self.calls += 1
        if self.calls == 1:
            time.sleep(self.wall_s)
            return False
        return True


def test_service_replan_ci_a_slow_planning_process_moves_the_replan_start_further_ahead() -> None:
    # A clean-clone CI run: the re-plan came back after the vehicle had reached its start, the
    # trajectory waited there, and the commanded speed fell to 0 mid-leg. The check's own
    # round trip now sizes the lookahead, not only the last plan's time inside the planner.
    cfg = PlannerConfig()
    runner = MissionRunner(None, None, lambda: None, cfg)  # type: ignore[arg-type]
    runner.last_plan_ms = 20.0
    traj = time_parametrize(np.array([[0.0, 0.0], [8.0, 0.0]]), 1.0, runner.limits)
    runner.planning = _LoadedPlanning(wall_s=0.6)  # type: ignore[assignment]
    runner._version_of = lambda costmap: 1  # type: ignore[method-assign]

    free, t_start = asyncio.run(runner._check_ahead(traj, lambda: 2.0))

    assert not free and t_start is not None
    assert t_start - 2.0 >= 1.5 * 0.6 + 0.3 - 1e-6, t_start
