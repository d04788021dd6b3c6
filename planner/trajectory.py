"""Time parametrisation of a planned path under speed, acceleration and yaw-rate limits.

The vehicle flies exactly along the (checked) polyline at a constant altitude, so every
sampled position is on the path the planner validated. Along the path the speed follows a
trapezoidal profile per segment (accelerate, cruise, brake, each within ``max_accel``) between
vertex speeds found by a forward/backward pass. At a corner of turn angle ``theta`` the speed
is capped so that the change of the velocity vector, ``2 v sin(theta / 2)``, stays below
``corner_speed_jump_m_s``: sharp corners are taken slowly, gentle bends at full speed.

Yaw follows the direction of travel at no more than ``max_yaw_rate``: each heading change
is a constant-rate turn centred ``yaw_lead_m`` of path before its corner (pushed later if the
previous turn has not finished), so the camera looks into a turn before the vehicle takes it:
what lies on the inside of a corner, where a path rounding an obstacle passes closest to it,
is otherwise seen only once the vehicle is beside it, at the edge of the field of view or not
at all. Yaw may so lead or lag the direction of travel, which a multicopter does not mind.
Starting from rest, the vehicle first turns on the spot until its heading is within
``max_heading_error`` of the first segment: the camera is the only sensor, and a vehicle that
set off sideways or backwards would fly into space it has not looked at (at 60 deg/s a
reversal takes 3 s, over a metre of blind flight at cruise speed). Angles are in the map
frame (ENU: 0 = +x east, counter-clockwise positive).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from planner.config import PlannerConfig
from semmap.errors import PlanningError
from semmap.frames import wrap_angle_rad


@dataclass(frozen=True)
class TrajectoryLimits:
    """Kinematic limits of the vehicle (m/s, m/s^2, rad/s; corner jump in m/s)."""

    max_speed_m_s: float
    max_accel_m_s2: float
    max_yaw_rate_rad_s: float
    corner_speed_jump_m_s: float = 0.3
    #: Starting from rest, motion waits until the heading is within this of the first segment
    #: (``math.pi``: never waits).
    max_heading_error_rad: float = math.pi
    #: Each yaw turn is centred this far (metres of path) before its corner (0: on it).
    yaw_lead_m: float = 0.0
    #: The last ``final_approach_m`` of a path are flown at no more than
    #: ``final_approach_speed_m_s``: an autopilot that trails its setpoints (PX4 by about half
    #: a second) brakes late and overshoots the end of a path braked at ``max_accel``; crawling
    #: the last stretch lets it catch up first, so it stops on the goal (0: no final approach).
    final_approach_m: float = 0.0
    final_approach_speed_m_s: float = 0.3

    @classmethod
    def from_config(cls, config: PlannerConfig) -> "TrajectoryLimits":
        """The limits in a planner config (whose angles are in degrees)."""
        return cls(config.max_speed_m_s, config.max_accel_m_s2, math.radians(config.max_yaw_rate_deg_s),
                   config.corner_speed_jump_m_s, math.radians(config.max_heading_error_deg), config.yaw_lead_m,
                   config.final_approach_m, config.final_approach_speed_m_s)

    def __post_init__(self) -> None:
        for name in ("max_speed_m_s", "max_accel_m_s2", "max_yaw_rate_rad_s", "corner_speed_jump_m_s",
                     "final_approach_speed_m_s"):
            v = getattr(self, name)
            if not (v > 0.0 and math.isfinite(v)):
                raise PlanningError(f"trajectory limit {name} must be a positive number (got {v})")
        if not 0.0 <= self.max_heading_error_rad <= math.pi:
            raise PlanningError(f"max_heading_error_rad must be in [0, pi] (got {self.max_heading_error_rad})")
        for name in ("yaw_lead_m", "final_approach_m"):
            v = getattr(self, name)
            if not (v >= 0.0 and math.isfinite(v)):
                raise PlanningError(f"trajectory limit {name} must be a finite number >= 0 (got {v})")


@dataclass(frozen=True)
class TrajectorySample:
    """The setpoint at one time: position and velocity in the map frame (ENU), yaw."""

    t_s: float
    position_m: NDArray[np.float64]  # (3,) x, y, z
    velocity_m_s: NDArray[np.float64]  # (3,)
    yaw_rad: float
    yaw_rate_rad_s: float


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A time-parametrised path; build with :func:`time_parametrize`, read with :meth:`sample`."""

    waypoints_xy_m: NDArray[np.float64]  # (K, 2)
    altitude_m: float
    limits: TrajectoryLimits
    seg_t0_s: NDArray[np.float64]  # (K-1,) start time of each segment
    seg_len_m: NDArray[np.float64]  # (K-1,)
    seg_dir: NDArray[np.float64]  # (K-1, 2) unit direction
    vertex_speed_m_s: NDArray[np.float64]  # (K,)
    seg_peak_m_s: NDArray[np.float64]  # (K-1,) top speed within the segment
    seg_phase_s: NDArray[np.float64]  # (K-1, 3) accelerate, cruise, brake durations
    yaw_turns: NDArray[np.float64]  # (M, 4) start time, end time, yaw from, yaw to (unwrapped)
    initial_yaw_rad: float
    motion_end_s: float

    @property
    def duration_s(self) -> float:
        """Time until the vehicle stands at the goal with its final yaw."""
        end = self.motion_end_s
        if len(self.yaw_turns):
            end = max(end, float(self.yaw_turns[-1, 1]))
        return end

    @property
    def length_m(self) -> float:
        return float(self.seg_len_m.sum())

    def _along(self, t_s: float) -> tuple[int, float, float]:
        """(segment, distance into it, speed) at time t (clamped to the motion)."""
        n = len(self.seg_len_m)
        if n == 0:
            return 0, 0.0, 0.0
        if t_s >= self.motion_end_s:
            return n - 1, float(self.seg_len_m[-1]), 0.0
        t = max(t_s, 0.0)
        i = int(np.searchsorted(self.seg_t0_s, t, side="right") - 1)
        i = min(max(i, 0), n - 1)
        tau = max(t - float(self.seg_t0_s[i]), 0.0)  # before seg 0 starts: turning on the spot
        a = self.limits.max_accel_m_s2
        v0, vp = float(self.vertex_speed_m_s[i]), float(self.seg_peak_m_s[i])
        ta, tc, tb = (float(x) for x in self.seg_phase_s[i])
        if tau <= ta:
            return i, v0 * tau + 0.5 * a * tau * tau, v0 + a * tau
        s = v0 * ta + 0.5 * a * ta * ta
        if tau <= ta + tc:
            return i, s + vp * (tau - ta), vp
        s += vp * tc
        u = min(tau - ta - tc, tb)
        return i, min(s + vp * u - 0.5 * a * u * u, float(self.seg_len_m[i])), max(vp - a * u, 0.0)

    def _yaw(self, t_s: float) -> tuple[float, float]:
        yaw = self.initial_yaw_rad
        for t0, t1, y0, y1 in self.yaw_turns:
            if t_s >= t1:
                yaw = y1
                continue
            if t_s > t0:
                frac = (t_s - t0) / max(t1 - t0, 1e-12)
                rate = (y1 - y0) / max(t1 - t0, 1e-12)
                return wrap_angle_rad(y0 + frac * (y1 - y0)), rate
            break
        return wrap_angle_rad(yaw), 0.0

    def sample(self, t_s: float) -> TrajectorySample:
        """The setpoint at ``t_s`` seconds after the start (clamped to [0, duration])."""
        i, s, v = self._along(t_s)
        if len(self.seg_len_m) == 0:
            xy = self.waypoints_xy_m[0]
            d = np.zeros(2)
        else:
            d = self.seg_dir[i]
            xy = self.waypoints_xy_m[i] + s * d
        yaw, rate = self._yaw(t_s)
        return TrajectorySample(
            t_s=float(t_s),
            position_m=np.array([xy[0], xy[1], self.altitude_m]),
            velocity_m_s=np.array([v * d[0], v * d[1], 0.0]),
            yaw_rad=yaw, yaw_rate_rad_s=rate,
        )


def _time_into_segment(x: float, v0: float, vp: float, phase: NDArray[np.float64], a: float) -> float:
    """Seconds from a segment's start until ``x`` metres of it are flown (the inverse of the
    trapezoid :meth:`Trajectory._along` reads)."""
    ta, tc, tb = (float(v) for v in phase)
    sa = v0 * ta + 0.5 * a * ta * ta
    if x <= sa:
        return (math.sqrt(max(v0 * v0 + 2.0 * a * max(x, 0.0), 0.0)) - v0) / a
    sc = sa + vp * tc
    if x <= sc:
        return ta + (x - sa) / vp
    u = (vp - math.sqrt(max(vp * vp - 2.0 * a * (x - sc), 0.0))) / a
    return ta + tc + min(u, tb)


def _segment_profile(L: float, v0: float, v1: float, vmax: float, a: float) -> tuple[float, float, float, float]:
    """(peak speed, accelerate, cruise, brake durations) of a trapezoid over length L."""
    vp = min(vmax, math.sqrt(max((2.0 * a * L + v0 * v0 + v1 * v1) / 2.0, 0.0)))
    vp = max(vp, v0, v1)
    ta = (vp - v0) / a
    tb = (vp - v1) / a
    d = L - (vp * vp - v0 * v0) / (2.0 * a) - (vp * vp - v1 * v1) / (2.0 * a)
    tc = max(d, 0.0) / vp if vp > 0.0 else 0.0
    return vp, ta, tc, tb


def _split_for_approach(p: NDArray[np.float64], approach_m: float) -> tuple[NDArray[np.float64], int]:
    """``p`` with a vertex ``approach_m`` of path before its end (unless one lies within a
    millimetre of there), and the index of the first segment of the final approach."""
    n = len(p) - 1
    if approach_m <= 0.0 or n < 1:
        return p, n
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    at = float(arc[-1]) - approach_m
    if at <= 1e-3:
        return p, 0
    k = int(np.searchsorted(arc, at, side="right")) - 1  # the segment the approach starts in
    if at - float(arc[k]) <= 1e-3:
        return p, k
    if float(arc[k + 1]) - at <= 1e-3:
        return p, k + 1
    split = p[k] + (p[k + 1] - p[k]) * ((at - float(arc[k])) / (float(arc[k + 1]) - float(arc[k])))
    return np.vstack([p[:k + 1], split[None, :], p[k + 1:]]), k + 1


def time_parametrize(
    path_xy_m: NDArray[np.floating],
    altitude_m: float,
    limits: TrajectoryLimits,
    initial_yaw_rad: float | None = None,
    initial_speed_m_s: float = 0.0,
) -> Trajectory:
    """Trajectory along a (K, 2) map-frame polyline at ``altitude_m``, from rest to rest.

    ``initial_yaw_rad``: the vehicle's yaw at the start (default: the first segment's
    heading); the first turn starts at t = 0. ``initial_speed_m_s``: start already moving
    along the first segment at this speed (a re-plan spliced into a flight), capped by the
    speed limit and by what the vehicle can still brake from within the path. The last
    ``limits.final_approach_m`` of the path are flown at ``limits.final_approach_speed_m_s``
    at most (a vertex is added where that stretch begins).
    """
    p, approach_from = _split_for_approach(_distinct_vertices(path_xy_m), limits.final_approach_m)
    seg = np.diff(p, axis=0)
    L = np.linalg.norm(seg, axis=1)
    n = len(L)
    u = seg / L[:, None] if n else np.zeros((0, 2))
    heading = np.arctan2(u[:, 1], u[:, 0]) if n else np.zeros(0)
    vmax, a = limits.max_speed_m_s, limits.max_accel_m_s2
    # Per segment: the speed limit, lowered on the final approach.
    seg_vmax = np.full(n, vmax)
    seg_vmax[approach_from:] = min(vmax, limits.final_approach_speed_m_s)
    v = _vertex_speeds(u, L, approach_from, limits, initial_speed_m_s)

    # Yaw at the start; from rest, wait for the first turn to face (nearly) along the path.
    omega = limits.max_yaw_rate_rad_s
    yaw0 = float(heading[0]) if initial_yaw_rad is None and n else float(initial_yaw_rad or 0.0)
    t = 0.0
    if n and v[0] <= 1e-6:
        error0 = abs(wrap_angle_rad(float(heading[0]) - yaw0))
        t = max(0.0, error0 - limits.max_heading_error_rad) / omega
    peak = np.zeros(n)
    phase = np.zeros((n, 3))
    t0 = np.zeros(n)
    for k in range(n):
        vp, ta, tc, tb = _segment_profile(float(L[k]), float(v[k]), float(v[k + 1]), float(seg_vmax[k]), a)
        peak[k] = vp
        phase[k] = (ta, tc, tb)
        t0[k] = t
        t += ta + tc + tb
    s_start = np.concatenate([[0.0], np.cumsum(L)])  # (n + 1,) arc length at each vertex

    def time_at(arc_m: float) -> float:
        j = int(np.clip(np.searchsorted(s_start, arc_m, side="right") - 1, 0, max(n - 1, 0)))
        return float(t0[j]) + _time_into_segment(arc_m - float(s_start[j]), float(v[j]), float(peak[j]), phase[j], a)

    return Trajectory(
        waypoints_xy_m=p, altitude_m=float(altitude_m), limits=limits, seg_t0_s=t0, seg_len_m=L,
        seg_dir=u, vertex_speed_m_s=v, seg_peak_m_s=peak, seg_phase_s=phase,
        yaw_turns=_yaw_turns(heading, s_start, time_at, yaw0, limits), initial_yaw_rad=yaw0,
        motion_end_s=t,
    )


def _distinct_vertices(path_xy_m: NDArray[np.floating]) -> NDArray[np.float64]:
    """The (K, 2) path without repeated vertices, or a :class:`PlanningError` for an empty
    or non-finite one."""
    p = np.asarray(path_xy_m, dtype=np.float64).reshape(-1, 2)
    if len(p) == 0 or not np.all(np.isfinite(p)):
        raise PlanningError(f"path must be a non-empty (K, 2) array of finite metres, got shape {p.shape}")
    keep = np.ones(len(p), dtype=bool)
    keep[1:] = np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-6
    return p[keep]


def _vertex_speeds(u: NDArray[np.float64], L: NDArray[np.float64], approach_from: int,
                   limits: TrajectoryLimits, initial_speed_m_s: float) -> NDArray[np.float64]:
    """(n + 1,) speed at each vertex: the speed limits, the corner limits, and what the
    acceleration allows forwards from the start and backwards from the stop at the end."""
    n = len(L)
    vmax, a = limits.max_speed_m_s, limits.max_accel_m_s2
    v = np.full(n + 1, vmax)
    v[approach_from:] = np.minimum(v[approach_from:], min(vmax, limits.final_approach_speed_m_s))
    v[0] = min(vmax, max(0.0, float(initial_speed_m_s))) if n else 0.0
    v[-1] = 0.0
    for k in range(1, n):
        cos_t = float(np.clip(np.dot(u[k - 1], u[k]), -1.0, 1.0))
        half = 0.5 * math.acos(cos_t)
        if half > 1e-9:
            v[k] = min(v[k], limits.corner_speed_jump_m_s / (2.0 * math.sin(half)))
    for k in range(n):
        v[k + 1] = min(v[k + 1], math.sqrt(v[k] ** 2 + 2.0 * a * L[k]))
    for k in range(n - 1, -1, -1):
        v[k] = min(v[k], math.sqrt(v[k + 1] ** 2 + 2.0 * a * L[k]))
    return v


def _yaw_turns(heading: NDArray[np.float64], s_start: NDArray[np.float64], time_at: Callable[[float], float],
               yaw0: float, limits: TrajectoryLimits) -> NDArray[np.float64]:
    """(T, 4) yaw turns (start s, end s, from rad, to rad) at the yaw rate limit: one to the
    first heading at t = 0, then one per corner centred ``yaw_lead_m`` before it (``time_at``
    maps arc length to time), never overlapping the previous one."""
    omega = limits.max_yaw_rate_rad_s
    turns: list[tuple[float, float, float, float]] = []
    current = yaw0
    free_at = 0.0
    if len(heading):
        delta = wrap_angle_rad(float(heading[0]) - current)
        if abs(delta) > 1e-9:
            d = abs(delta) / omega
            turns.append((0.0, d, current, current + delta))
            current += delta
            free_at = d
    for k in range(1, len(heading)):
        delta = wrap_angle_rad(float(heading[k]) - wrap_angle_rad(current))
        if abs(delta) <= 1e-9:
            continue
        d = abs(delta) / omega
        centre = time_at(max(float(s_start[k]) - limits.yaw_lead_m, 0.0))
        start = max(centre - d / 2.0, free_at)
        turns.append((start, start + d, current, current + delta))
        current += delta
        free_at = start + d
    return np.array(turns, dtype=np.float64).reshape(-1, 4)
