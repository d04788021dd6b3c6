"""Scripted trajectories through simulated rooms: clearance, yaw-rate limit, routing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.errors import SimulationError
from companion.sim.trajectory import (
    Keyframe,
    Trajectory,
    blocking_objects,
    check_clearance,
    doorway_transit,
    fly_route,
    lawnmower,
    perimeter_loop,
    plan_route,
)
from companion.sim.world import generate_room


def yaw_rates_rad_s(traj: Trajectory, rate_hz: float = 100.0) -> np.ndarray:
    t = traj.start_s + np.arange(0.0, traj.duration_s, 1.0 / rate_hz)
    yaw = np.unwrap([traj.state_at(float(x))[1] for x in t])
    return np.abs(np.diff(yaw)) * rate_hz


def speeds_m_s(traj: Trajectory, rate_hz: float = 50.0) -> np.ndarray:
    return np.linalg.norm(np.diff(traj.positions_m(rate_hz), axis=0), axis=1) * rate_hz


def test_keyframes_interpolate_and_clamp() -> None:
    traj = Trajectory([Keyframe(0.0, 0.0, 0.0, 1.0, math.radians(170)), Keyframe(2.0, 2.0, 0.0, 1.0, math.radians(-170))])
    xyz, yaw = traj.state_at(1.0)
    assert np.allclose(xyz, [1.0, 0.0, 1.0])
    assert abs(math.degrees(yaw)) == pytest.approx(180.0)  # the short way round, through 180
    assert np.allclose(traj.state_at(-5.0)[0], [0, 0, 1]) and np.allclose(traj.state_at(9.0)[0], [2, 0, 1])
    T = traj.T_map_body(2.0)
    assert np.allclose(T[:3, 3], [2, 0, 1]) and T[2, 2] == pytest.approx(1.0)  # level
    assert len(traj.samples(10.0)) == 21
    provider = traj.pose_provider(1.0)
    stamps = []
    while (s := provider()) is not None:
        stamps.append(s[0])
    assert stamps == [0.0, 1.0, 2.0]
    with pytest.raises(SimulationError, match="time order"):
        Trajectory([Keyframe(1.0, 0, 0, 0, 0), Keyframe(0.5, 0, 0, 0, 0)])


def test_fly_route_respects_speed_and_yaw_rate_with_sweep() -> None:
    route = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 0.0]])
    limit = math.radians(60)
    traj = fly_route(route, 1.0, speed_m_s=0.5, yaw_rate_max_rad_s=limit,
                     yaw_sweep_rad=math.radians(20), sweep_period_s=5.0)
    assert yaw_rates_rad_s(traj).max() <= limit * 1.02
    assert speeds_m_s(traj).max() <= 0.5 * 1.02
    assert np.allclose(traj.state_at(traj.start_s + traj.duration_s)[0][:2], [0.0, 0.0])
    with pytest.raises(SimulationError, match="sweep"):
        fly_route(route, 1.0, yaw_rate_max_rad_s=math.radians(30), yaw_sweep_rad=math.radians(40), sweep_period_s=4.0)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_doorway_transit_keeps_clear_and_connects_the_doorways(seed: int) -> None:
    room = generate_room(seed)
    traj = doorway_transit(room, 0.6, clearance_required_m=0.5, min_clearance_m=0.3)
    start, _ = traj.state_at(traj.start_s)
    end, _ = traj.state_at(traj.start_s + traj.duration_s)
    assert np.linalg.norm(start[:2] - np.array(room.doorways[0].inside_point_m(0.6))) < 0.5
    assert np.linalg.norm(end[:2] - np.array(room.doorways[1].inside_point_m(0.6))) < 0.5
    assert check_clearance(room, traj, 0.3) >= 0.3
    assert yaw_rates_rad_s(traj).max() <= math.radians(60) * 1.02
    # No flying under tables: every blocking object's footprint stays outside the path.
    assert blocking_objects(room, 0.6, 0.15, 0.1)


def test_lawnmower_and_loop_cover_the_room_clear_of_furniture() -> None:
    room = generate_room(4)
    mow = lawnmower(room, 1.0, lane_spacing_m=1.0)
    pos = mow.positions_m(5.0)
    assert pos[:, 0].max() - pos[:, 0].min() > room.width_m * 0.6
    assert pos[:, 1].max() - pos[:, 1].min() > room.depth_m * 0.6
    assert check_clearance(room, mow, 0.3) >= 0.3
    loop = perimeter_loop(room, 1.0)
    a, _ = loop.state_at(loop.start_s)
    b, _ = loop.state_at(loop.start_s + loop.duration_s)
    assert np.linalg.norm(a - b) < 0.3
    assert check_clearance(room, loop, 0.3) >= 0.3
    assert np.all(np.abs(pos[:, 2] - 1.0) < 1e-9)


@pytest.mark.parametrize("seed", [8, 27])
def test_coverage_flights_skip_corners_closed_off_by_furniture(seed: int) -> None:
    # In these rooms furniture at 1 m closes off a corner: the flights stay in the main region.
    room = generate_room(seed)
    for build in (lawnmower, perimeter_loop):
        traj = build(room, 1.0)
        assert check_clearance(room, traj, 0.3) >= 0.3
        assert traj.duration_s > 20.0


def test_route_avoids_whole_footprints_of_blocking_furniture() -> None:
    room = generate_room(0, n_objects=10, class_names=["desk", "conference_table", "coffee_table"])
    altitude = 0.66  # band 0.485-0.835 m: meets table tops (>= 0.72), clears coffee tables (<= 0.48)
    blockers = blocking_objects(room, altitude, 0.15, 0.1)
    assert {o.class_name for o in blockers} <= {"desk", "conference_table"}
    route = plan_route(room, [(0.5, 0.5), (room.width_m - 0.5, room.depth_m - 0.5)], altitude, 0.3)
    traj = fly_route(route, altitude)
    assert check_clearance(room, traj, 0.3) >= 0.3  # includes the footprints
    # Ignoring footprints (vertical_margin_m=None) only the legs count: never less clear.
    assert check_clearance(room, traj, 0.0, vertical_margin_m=None) >= check_clearance(room, traj, 0.0)


def test_impossible_clearance_is_an_error() -> None:
    room = generate_room(0, 4.0, 3.0, n_objects=2)
    with pytest.raises(SimulationError, match="clearance"):
        plan_route(room, [(1.0, 1.0), (3.0, 2.0)], 1.0, clearance_required_m=2.0)
    with pytest.raises(SimulationError):
        doorway_transit(room, 1.0, clearance_required_m=2.0, min_clearance_m=None)
