"""Flying one planned trajectory of a leg: the setpoint stream, arrival, and re-plans in flight.

:class:`LegFollow` feeds a :class:`~planner.trajectory.Trajectory` into the offboard
controller's setpoint slot, one named step per tick: advance trajectory time while the
controller flies our setpoints (:meth:`LegFollow.advance`), send the setpoint
(:meth:`LegFollow.send_setpoint`), judge arrival (:meth:`LegFollow.arrival`), splice in a
finished re-plan (:meth:`LegFollow.splice_replan`) and check the path ahead on the newest
costmap (:meth:`LegFollow.check_path_ahead`), which the planning process judges exactly as
the planner judges its own paths.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from companion.mavlink.failsafe import OffboardState, PositionSetpoint
from companion.mavlink.state import VehicleState
from companion.service.mission_legs import (
    FEED_PERIOD_S,
    Leg,
    LegReport,
    arrived,
    map_frame_of,
    position_enu,
)
from planner.trajectory import Trajectory, TrajectorySample, time_parametrize
from planner.types import PlanResult
from semmap.costmap import Costmap
from semmap.frames import enu_to_ned, yaw_enu_to_ned

if TYPE_CHECKING:
    from companion.service.mission_runner import MissionRunner

log = logging.getLogger(__name__)

#: How often the remaining path is checked against the newest costmap.
CHECK_PERIOD_S = 0.5
#: A trajectory counts as "late" this long after its end with the vehicle not arrived (s).
LATE_AFTER_S = 5.0


class LegFollow:
    """One trajectory flown for :meth:`MissionRunner._follow` (see there for the outcomes).

    Trajectory time only advances while the controller flies our setpoints (ACTIVE), so
    after a hold (stale pose or map, link loss) the vehicle resumes where it stopped. While a
    re-plan in flight is pending, the trajectory brakes to rest at the point the re-plan
    starts from (:meth:`brake_at`) and ends there."""

    def __init__(self, runner: MissionRunner, traj: Trajectory, leg: Leg, check: bool,
                 capture_mono_s: float | None, rep: LegReport | None) -> None:
        self.runner = runner
        self.traj = traj
        self.leg = leg
        self.check = check
        self.capture_mono_s = capture_mono_s
        self.rep = rep
        self.goal = np.array(leg.goal_xy_m)
        self.t_traj = 0.0
        self.last = time.monotonic()
        self.next_check = self.last + CHECK_PERIOD_S
        self.checking: asyncio.Task[tuple[bool, float | None]] | None = None
        self.replan: asyncio.Task[tuple[PlanResult, Costmap]] | None = None

    async def run(self) -> str:
        """Fly until an outcome: "reached", "invalid", "tracking" or "late"."""
        try:
            while True:
                now = time.monotonic()
                outcome = await self.advance(now)
                if outcome is not None:
                    return outcome
                s = self.send_setpoint()
                snap = self.runner.vehicle.snapshot()
                outcome = self.arrival(snap)
                if outcome is not None:
                    return outcome
                if self.replan is not None and self.replan.done():
                    if not self.splice_replan(now, s):
                        return "invalid"
                    continue
                if self.check and self.replan is None:
                    outcome = self.check_path_ahead(now, position_enu(snap))
                    if outcome is not None:
                        return outcome
                await asyncio.sleep(FEED_PERIOD_S)
        finally:
            for task in (self.checking, self.replan):
                if task is not None and not task.done():
                    task.cancel()

    async def advance(self, now: float) -> str | None:
        """Advance trajectory time by the time flown in OFFBOARD since the last tick; an
        outcome when the controller is not flying our setpoints: "tracking" (held for a
        vehicle that did not follow), "invalid" (the position estimate jumped, or the link is
        back after PX4's failsafe moved the vehicle: re-plan from where it is)."""
        ctl = self.runner.vehicle.offboard
        st = ctl.state
        if st is OffboardState.ACTIVE:
            self.t_traj += now - self.last
        elif st is OffboardState.HOLDING and ctl.failsafe.tracking_fault:
            return "tracking"
        elif st is OffboardState.HOLDING and ctl.failsafe.take_position_reset():
            # The rest of this trajectory was planned in the estimate before the jump.
            pos = position_enu(self.runner.vehicle.snapshot())
            if pos is not None:
                self.runner.hold_at(pos[:2], self.leg.altitude_m)
            log.warning("leg %d: the position estimate jumped; re-planning from where the vehicle is", self.leg.seq)
            return "invalid"
        elif st is OffboardState.LINK_LOST and self.runner.vehicle.connected:
            await self.runner._reengage(self.leg)
            return "invalid"
        else:
            self.runner._check_offboard()
        self.last = now
        return None

    def send_setpoint(self) -> TrajectorySample:
        """Hand the trajectory's setpoint at the current time to the setpoint stream (and
        record the plan's frame-to-setpoint latency with its first one)."""
        runner = self.runner
        s = self.traj.sample(self.t_traj)
        n, e, d = map_frame_of(runner.vehicle.snapshot()).to_ned(*(float(v) for v in s.position_m))
        vn, ve, vd = enu_to_ned(*(float(v) for v in s.velocity_m_s))
        runner.vehicle.offboard.set_setpoint(PositionSetpoint((n, e, d), yaw_rad=yaw_enu_to_ned(s.yaw_rad),
                                                              velocity_ned_m_s=(vn, ve, vd)))
        if self.capture_mono_s is not None:
            runner.frame_to_setpoint_ms.append(1e3 * (time.monotonic() - self.capture_mono_s))
            self.capture_mono_s = None
        return s

    def arrival(self, snap: VehicleState) -> str | None:
        """At the trajectory's end (no re-plan pending): "reached" once the vehicle has
        arrived at rest, "late" when it has not :data:`LATE_AFTER_S` later."""
        if self.replan is None and self.t_traj >= self.traj.duration_s and position_enu(snap) is not None:
            if arrived(snap, self.goal, self.leg.acceptance_m):
                return "reached"
            if self.t_traj >= self.traj.duration_s + LATE_AFTER_S:
                return "late"
        return None

    def splice_replan(self, now: float, s: TrajectorySample) -> bool:
        """The re-plan in flight is back: splice its path onto the current trajectory at its
        start point, at the current speed (True); False when it failed or moved the goal
        (stop and re-plan from here)."""
        assert self.replan is not None
        runner, leg, rep = self.runner, self.leg, self.rep
        result, costmap = self.replan.result()
        self.replan = None
        if rep is not None:
            rep.plans += 1
            rep.plan_ms.append(1e3 * result.planning_time_s)
        if not result.ok or result.snapped_goal:
            log.info("leg %d: re-plan on the fly gave %s; stopping to re-plan from here",
                     leg.seq, result.status.value if not result.ok else "a moved goal")
            return False
        path = np.vstack([_between(self.traj, self.t_traj, self.traj.duration_s), result.path_xy_m])
        speed = float(np.linalg.norm(s.velocity_m_s[:2]))
        self.traj = time_parametrize(path, leg.altitude_m, runner.limits, initial_yaw_rad=s.yaw_rad,
                                     initial_speed_m_s=speed)
        self.t_traj = 0.0
        self.next_check = now + CHECK_PERIOD_S
        self.capture_mono_s = runner.capture_time(costmap) if runner.capture_time is not None else None
        if runner.on_path is not None:
            runner.on_path(path)
        return True

    def brake_at(self, t_stop_s: float) -> None:
        """Re-time the trajectory from now to ``t_stop_s`` to come to rest there, where it now
        ends (its samples hold at the end): a re-plan that comes back late must find the vehicle
        stopped at the new path's start, not handed a frozen setpoint with the cruise
        velocity as feed-forward (PX4 then carries on past it, towards the obstacle)."""
        s = self.traj.sample(self.t_traj)
        stretch = _between(self.traj, self.t_traj, t_stop_s)
        self.traj = time_parametrize(stretch, self.leg.altitude_m, self.runner.limits, initial_yaw_rad=s.yaw_rad,
                                     initial_speed_m_s=float(np.linalg.norm(s.velocity_m_s[:2])))
        self.t_traj = 0.0

    def check_path_ahead(self, now: float, pos: NDArray[np.float64] | None) -> str | None:
        """Every :data:`CHECK_PERIOD_S`, check the rest of the path on the newest costmap (in
        the planning process, off this loop). When it has become blocked, re-plan *without
        stopping* from a point a little ahead, braking to rest there should the plan not be
        back by then; "invalid" (stop and re-plan from here) when even the stretch just ahead is
        blocked."""
        runner, leg, rep, traj = self.runner, self.leg, self.rep, self.traj
        if self.checking is None and now >= self.next_check and pos is not None and self.t_traj < traj.duration_s:
            self.checking = asyncio.create_task(runner._check_ahead(traj, lambda: self.t_traj))
        elif self.checking is not None and self.checking.done():
            free, t_start = self.checking.result()
            self.checking = None
            self.next_check = now + CHECK_PERIOD_S
            if not free:
                if rep is not None:
                    rep.replans_invalid += 1
                if t_start is None or t_start <= self.t_traj:
                    log.info("leg %d: the path just ahead crosses a newly mapped obstacle; "
                             "stopping to re-plan", leg.seq)
                    return "invalid"
                start = traj.sample(t_start).position_m[:2]
                log.info("leg %d: the path ahead crosses a newly mapped obstacle; re-planning "
                         "from (%.2f, %.2f) m, %.1f s ahead, while flying on", leg.seq,
                         start[0], start[1], t_start - self.t_traj)
                self.brake_at(t_start)
                self.replan = asyncio.create_task(runner._plan(np.asarray(start, dtype=np.float64),
                                                               leg.goal_xy_m, replan=True))
        return None


def _remaining(traj: Trajectory, t_s: float) -> NDArray[np.float64]:
    """(K, 2) the rest of the trajectory's path from a little ahead of time ``t_s`` (the
    vehicle's own neighbourhood is not judged: it is where the vehicle already is)."""
    t_ahead = min(traj.duration_s, t_s + 0.3)
    ahead = traj.sample(t_ahead).position_m[:2]
    seg = max(0, int(np.searchsorted(traj.seg_t0_s, t_ahead, side="right")) - 1)
    return np.vstack([ahead[None, :], traj.waypoints_xy_m[seg + 1:]])


def _between(traj: Trajectory, t0_s: float, t1_s: float) -> NDArray[np.float64]:
    """(K, 2) the trajectory's path from time ``t0_s`` to ``t1_s`` (its corners in between)."""
    t1_s = min(t1_s, traj.duration_s)
    a = traj.sample(t0_s).position_m[:2]
    b = traj.sample(t1_s).position_m[:2]
    s0 = max(0, int(np.searchsorted(traj.seg_t0_s, t0_s, side="right")) - 1)
    s1 = max(0, int(np.searchsorted(traj.seg_t0_s, t1_s, side="right")) - 1)
    return np.vstack([a[None, :], traj.waypoints_xy_m[s0 + 1:s1 + 1], b[None, :]])
