"""Trajectory time parametrisation: limits hold, the vehicle stays on the path, ends at rest."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planner.config import PlannerConfig
from planner.trajectory import TrajectoryLimits, time_parametrize
from semmap.errors import PlanningError

LIMITS = TrajectoryLimits(max_speed_m_s=1.0, max_accel_m_s2=0.8, max_yaw_rate_rad_s=math.radians(60),
                          corner_speed_jump_m_s=0.3)


def _dist_to_polyline(p: np.ndarray, poly: np.ndarray) -> float:
    a, b = poly[:-1], poly[1:]
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12), 0, 1)
    return float(np.min(np.linalg.norm(a + t[:, None] * ab - p, axis=1)))


def _samples(traj, dt=0.01):
    ts = np.arange(0.0, traj.duration_s + dt, dt)
    return ts, [traj.sample(float(t)) for t in ts]


paths = st.lists(st.tuples(st.floats(-5, 5), st.floats(-5, 5)), min_size=2, max_size=6).map(
    lambda pts: np.array(pts, dtype=np.float64)
).filter(lambda p: np.linalg.norm(np.diff(p, axis=0), axis=1).min() > 0.05)


@settings(max_examples=30, deadline=None)
@given(paths)
def test_limits_hold_and_position_stays_on_path(path: np.ndarray) -> None:
    traj = time_parametrize(path, 1.2, LIMITS)
    ts, samples = _samples(traj)
    speeds = np.array([np.linalg.norm(s.velocity_m_s) for s in samples])
    assert speeds.max() <= LIMITS.max_speed_m_s + 1e-9
    for s in samples[:: max(1, len(samples) // 50)]:
        assert _dist_to_polyline(s.position_m[:2], path) < 1e-6
        assert s.position_m[2] == pytest.approx(1.2)
    # Speed changes within max_accel (velocity direction jumps only at corners).
    dv = np.abs(np.diff(speeds)) / np.diff(ts)
    assert dv.max() <= LIMITS.max_accel_m_s2 * 1.02 + 1e-6
    # Yaw rate within the limit (unwrapped finite differences).
    yaw = np.unwrap([s.yaw_rad for s in samples])
    assert np.max(np.abs(np.diff(yaw) / np.diff(ts))) <= LIMITS.max_yaw_rate_rad_s * 1.01 + 1e-6
    # Starts and ends at rest at the path's ends.
    np.testing.assert_allclose(samples[0].position_m[:2], path[0], atol=1e-9)
    np.testing.assert_allclose(traj.sample(traj.duration_s).position_m[:2], path[-1], atol=1e-6)
    assert np.linalg.norm(traj.sample(traj.duration_s).velocity_m_s) == 0.0
    assert speeds[0] == 0.0


def test_straight_line_reaches_cruise_speed_and_takes_trapezoid_time() -> None:
    traj = time_parametrize(np.array([[0.0, 0.0], [10.0, 0.0]]), 1.0, LIMITS)
    # accelerate 1.25 s over 0.625 m, cruise 8.75 m, brake 1.25 s.
    assert traj.motion_end_s == pytest.approx(1.25 + 8.75 + 1.25)
    assert np.linalg.norm(traj.sample(5.0).velocity_m_s) == pytest.approx(1.0)


def test_sharp_corner_is_slow_gentle_bend_is_fast() -> None:
    sharp = time_parametrize(np.array([[0.0, 0.0], [5.0, 0.0], [5.0, 5.0]]), 1.0, LIMITS)
    gentle = time_parametrize(np.array([[0.0, 0.0], [5.0, 0.0], [10.0, 0.2]]), 1.0, LIMITS)
    assert sharp.vertex_speed_m_s[1] == pytest.approx(0.3 / (2 * math.sin(math.pi / 4)))
    assert gentle.vertex_speed_m_s[1] == pytest.approx(1.0)
    # Velocity jump at the corner stays within the configured bound.
    t_corner = sharp.seg_t0_s[1]
    before = sharp.sample(t_corner - 1e-6).velocity_m_s
    after = sharp.sample(t_corner + 1e-6).velocity_m_s
    assert np.linalg.norm(after - before) <= 0.3 + 1e-3


def test_yaw_follows_direction_of_travel() -> None:
    traj = time_parametrize(np.array([[0.0, 0.0], [5.0, 0.0], [5.0, 5.0]]), 1.0, LIMITS)
    assert traj.sample(1.0).yaw_rad == pytest.approx(0.0, abs=1e-9)
    assert traj.sample(traj.duration_s).yaw_rad == pytest.approx(math.pi / 2)


def test_initial_yaw_turns_at_limited_rate() -> None:
    traj = time_parametrize(np.array([[0.0, 0.0], [0.0, 3.0]]), 1.0, LIMITS, initial_yaw_rad=0.0)
    s = traj.sample(0.5)
    assert s.yaw_rad == pytest.approx(math.radians(30), abs=1e-6)
    assert s.yaw_rate_rad_s == pytest.approx(LIMITS.max_yaw_rate_rad_s)


def test_single_point_path_holds() -> None:
    traj = time_parametrize(np.array([[1.0, 2.0]]), 0.5, LIMITS)
    s = traj.sample(3.0)
    np.testing.assert_allclose(s.position_m, [1.0, 2.0, 0.5])
    assert traj.duration_s == 0.0


def test_limits_from_config_convert_degrees() -> None:
    lim = TrajectoryLimits.from_config(PlannerConfig(max_yaw_rate_deg_s=90.0, max_speed_m_s=2.0))
    assert lim.max_yaw_rate_rad_s == pytest.approx(math.pi / 2) and lim.max_speed_m_s == 2.0


def test_bad_input_raises() -> None:
    with pytest.raises(PlanningError):
        time_parametrize(np.array([[0.0, np.nan], [1.0, 1.0]]), 1.0, LIMITS)
    with pytest.raises(PlanningError):
        TrajectoryLimits(0.0, 1.0, 1.0)


def test_initial_speed_starts_moving_and_still_ends_at_rest() -> None:
    # A re-plan spliced into a flight starts at the vehicle's speed along the first segment.
    limits = TrajectoryLimits(max_speed_m_s=1.0, max_accel_m_s2=1.0, max_yaw_rate_rad_s=math.radians(60))
    path = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 2.0]])
    for v0, expect in ((0.0, 0.0), (0.6, 0.6), (5.0, 1.0)):
        traj = time_parametrize(path, 1.0, limits, initial_speed_m_s=v0)
        assert np.allclose(traj.sample(0.0).velocity_m_s[:2], [expect, 0.0])
        assert np.allclose(traj.sample(traj.duration_s).velocity_m_s, 0.0)
        assert np.allclose(traj.sample(traj.duration_s).position_m[:2], [3.0, 2.0])
    # On a path too short to brake from that speed, it starts only as fast as it can stop.
    short = time_parametrize(np.array([[0.0, 0.0], [0.1, 0.0]]), 1.0, limits, initial_speed_m_s=1.0)
    assert float(np.linalg.norm(short.sample(0.0).velocity_m_s)) <= math.sqrt(2 * 1.0 * 0.1) + 1e-9


def test_from_rest_it_turns_to_face_the_path_before_moving() -> None:
    # The path runs east; the vehicle faces west. With a 30 deg heading limit it turns 150 deg
    # on the spot (2.5 s at 60 deg/s) before setting off, and never moves heading more than
    # 30 deg off its direction of travel.
    limits = TrajectoryLimits(1.0, 0.8, math.radians(60), 0.3, max_heading_error_rad=math.radians(30))
    path = np.array([[0.0, 0.0], [3.0, 0.0]])
    traj = time_parametrize(path, 1.0, limits, initial_yaw_rad=math.pi)
    blind = time_parametrize(path, 1.0, LIMITS, initial_yaw_rad=math.pi)
    assert traj.duration_s == pytest.approx(blind.motion_end_s + 2.5, abs=1e-6)
    for t, s in zip(*_samples(traj), strict=True):
        moving = np.linalg.norm(s.velocity_m_s) > 1e-9
        if t < 2.5 - 1e-6:
            assert np.allclose(s.position_m[:2], path[0]) and not moving
        if moving:
            assert abs(math.remainder(s.yaw_rad - 0.0, 2 * math.pi)) <= math.radians(30) + 1e-6
    # The blind one sets off at once, facing backwards.
    s = blind.sample(0.5)
    assert np.linalg.norm(s.velocity_m_s) > 0.1 and abs(math.remainder(s.yaw_rad, 2 * math.pi)) > math.radians(100)
    # Already moving (a re-plan spliced into flight): no waiting.
    spliced = time_parametrize(path, 1.0, limits, initial_yaw_rad=math.pi, initial_speed_m_s=0.5)
    assert np.linalg.norm(spliced.sample(0.0).velocity_m_s) == pytest.approx(0.5)


def test_heading_limit_comes_from_the_planner_config() -> None:
    assert TrajectoryLimits.from_config(PlannerConfig()).max_heading_error_rad == pytest.approx(math.radians(30))
    with pytest.raises(PlanningError, match="max_heading_error_rad"):
        TrajectoryLimits(1.0, 1.0, 1.0, 0.3, max_heading_error_rad=4.0)


def _time_at_x(traj, x: float) -> float:
    """First sample time at which the vehicle has flown to ``x`` along a path starting +x."""
    ts, ss = _samples(traj, 0.005)
    return float(next(t for t, s in zip(ts, ss, strict=True) if s.position_m[0] >= x - 1e-9))


def test_yaw_lead_centres_each_turn_before_its_corner() -> None:
    """With ``yaw_lead_m`` the camera is half way through a turn that far before the corner
    (it looks into the turn before the vehicle takes it); without, on the corner."""
    path = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0]])
    on_corner = time_parametrize(path, 1.0, LIMITS)
    lead = time_parametrize(path, 1.0, TrajectoryLimits(1.0, 0.8, math.radians(60), 0.3, yaw_lead_m=1.0))
    assert on_corner.sample(_time_at_x(on_corner, 4.0)).yaw_rad == pytest.approx(math.pi / 4, abs=0.03)
    assert lead.sample(_time_at_x(lead, 3.0)).yaw_rad == pytest.approx(math.pi / 4, abs=0.03)
    # Arriving at the corner, the leading camera already faces the next segment.
    assert lead.sample(_time_at_x(lead, 4.0)).yaw_rad == pytest.approx(math.pi / 2, abs=1e-6)
    # Position and speed are those of the same path without a lead.
    for t in (0.5, 2.0, 5.0, 7.0):
        np.testing.assert_allclose(lead.sample(t).position_m, on_corner.sample(t).position_m)


def test_yaw_lead_keeps_turns_in_order_and_within_the_rate_limit() -> None:
    """Corners closer together than the lead: turns still follow one another at the limit."""
    path = np.array([[0.0, 0.0], [2.0, 0.0], [2.2, 0.3], [2.4, 0.0], [4.0, 0.0]])
    lim = TrajectoryLimits(1.0, 0.8, math.radians(60), 0.3, yaw_lead_m=0.8)
    traj = time_parametrize(path, 1.0, lim)
    turns = traj.yaw_turns
    assert np.all(turns[1:, 0] >= turns[:-1, 1] - 1e-9)
    ts, ss = _samples(traj)
    yaw = np.unwrap([s.yaw_rad for s in ss])
    assert np.max(np.abs(np.diff(yaw))) / 0.01 <= lim.max_yaw_rate_rad_s * (1 + 1e-6)
    assert ss[-1].yaw_rad == pytest.approx(0.0, abs=1e-9)


def test_yaw_lead_comes_from_the_planner_config_and_is_checked() -> None:
    assert TrajectoryLimits.from_config(PlannerConfig(yaw_lead_m=0.4)).yaw_lead_m == pytest.approx(0.4)
    with pytest.raises(PlanningError, match="yaw_lead_m"):
        TrajectoryLimits(1.0, 1.0, 1.0, yaw_lead_m=-0.1)


APPROACH = TrajectoryLimits(max_speed_m_s=1.0, max_accel_m_s2=1.0, max_yaw_rate_rad_s=math.radians(60),
                            final_approach_m=0.5, final_approach_speed_m_s=0.3)


@pytest.mark.parametrize("path", [[(0.0, 0.0), (3.0, 0.0)], [(0.0, 0.0), (2.0, 1.0), (2.2, 1.3)],
                                  [(0.0, 0.0), (0.3, 0.1)]])
def test_final_approach_is_flown_at_a_crawl_and_the_path_is_unchanged(path: list[tuple[float, float]]) -> None:
    p = np.array(path)
    traj = time_parametrize(p, 0.6, APPROACH, initial_yaw_rad=0.0)
    goal = p[-1]
    remaining = np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1)[::-1])[::-1]  # path left from each vertex
    assert traj.length_m == pytest.approx(float(remaining[0]))
    _ts, samples = _samples(traj)
    for s in samples:
        xy = s.position_m[:2]
        assert _dist_to_polyline(xy[None, :], p) < 1e-6
        # The path left to fly, measured along it: from the vertex after xy, or straight on the last segment.
        k = next((i for i in range(len(p) - 1) if _dist_to_polyline(xy[None, :], p[i:i + 2]) < 1e-6), len(p) - 2)
        left = float(np.linalg.norm(p[k + 1] - xy)) + (float(remaining[k + 1]) if k + 1 < len(remaining) else 0.0)
        if left < 0.5 - 1e-6:
            assert float(np.linalg.norm(s.velocity_m_s[:2])) <= 0.3 + 1e-6, (left, s.velocity_m_s)
    assert np.allclose(samples[-1].position_m[:2], goal)
    plain = time_parametrize(p, 0.6, TrajectoryLimits(1.0, 1.0, math.radians(60)), initial_yaw_rad=0.0)
    assert traj.duration_s > plain.duration_s  # the crawl costs time, a second or less


def test_final_approach_comes_from_the_planner_config_and_is_checked() -> None:
    lim = TrajectoryLimits.from_config(PlannerConfig(final_approach_m=0.4, final_approach_speed_m_s=0.25))
    assert (lim.final_approach_m, lim.final_approach_speed_m_s) == (0.4, 0.25)
    with pytest.raises(PlanningError, match="final_approach_m"):
        TrajectoryLimits(1.0, 1.0, 1.0, final_approach_m=-0.1)
    with pytest.raises(PlanningError, match="final_approach_speed_m_s"):
        TrajectoryLimits(1.0, 1.0, 1.0, final_approach_speed_m_s=0.0)
