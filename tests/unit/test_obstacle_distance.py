"""OBSTACLE_DISTANCE from a costmap: sector geometry (body FRD, clockwise), values, encoding."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink

from companion.mavlink.obstacle_distance import (
    N_SECTORS,
    UINT16_MAX,
    ObstacleDistanceScan,
    compute_obstacle_distances,
)
from semmap.costmap import FREE_SPACE, LETHAL_OBSTACLE, NO_INFORMATION, Costmap, VerticalBand
from semmap.grid import GridSpec

RES_M = 0.05
BAND = VerticalBand(0.5, 1.5)


def _room(fill: int = FREE_SPACE) -> tuple[GridSpec, np.ndarray]:
    spec = GridSpec(RES_M, (-6.0, -6.0), (240, 240))  # 12 m x 12 m around the origin
    return spec, np.full(spec.shape_rc, fill, dtype=np.uint8)


def _costmap(spec: GridSpec, cost: np.ndarray) -> Costmap:
    return Costmap(spec, cost, BAND)


def _put_block(spec: GridSpec, cost: np.ndarray, x0: float, x1: float, y0: float, y1: float) -> None:
    X, Y = spec.cell_centers_xy()
    cost[(X >= x0) & (X <= x1) & (Y >= y0) & (Y <= y1)] = LETHAL_OBSTACLE


def test_open_known_space_is_no_obstacle_everywhere() -> None:
    spec, cost = _room()
    scan = compute_obstacle_distances(_costmap(spec, cost), (0.0, 0.0), 0.0, max_distance_m=5.0)
    assert scan.distances_cm == (501,) * N_SECTORS  # max_distance + 1
    assert (scan.min_distance_cm, scan.max_distance_cm) == (20, 500)
    assert scan.increment_deg == pytest.approx(5.0)
    assert scan.frame == mavlink.MAV_FRAME_BODY_FRD


def test_unmapped_space_is_unknown_unless_told_otherwise() -> None:
    spec, cost = _room(NO_INFORMATION)
    cm = _costmap(spec, cost)
    assert compute_obstacle_distances(cm, (0.0, 0.0), 0.0).distances_cm == (UINT16_MAX,) * N_SECTORS
    scan = compute_obstacle_distances(cm, (0.0, 0.0), 0.0, unknown_is_obstacle=True)
    assert scan.distances_cm == (scan.min_distance_cm,) * N_SECTORS


def test_off_grid_counts_as_unmapped() -> None:
    spec, cost = _room()
    # 1 m from the east edge of the grid, 8 m range: eastward rays leave the map.
    scan = compute_obstacle_distances(_costmap(spec, cost), (5.0, 0.0), 0.0, max_distance_m=8.0)
    assert scan.distances_cm[0] == UINT16_MAX  # straight ahead (east) runs off the map
    scan = compute_obstacle_distances(_costmap(spec, cost), (5.0, 0.0), 0.0,
                                      max_distance_m=8.0, unknown_is_obstacle=True)
    assert scan.distances_cm[0] == pytest.approx(100, abs=RES_M * 100)


@pytest.mark.parametrize(
    ("yaw_map_rad", "expected_sector"),
    [
        (0.0, 0),  # facing east: the wall is dead ahead
        (math.pi / 2, 18),  # facing north: the wall is 90 deg to the right (clockwise)
        (math.pi, 36),  # facing west: behind
        (-math.pi / 2, 54),  # facing south: 270 deg clockwise = to the left
    ],
)
def test_sectors_are_body_frd_clockwise_from_the_nose(yaw_map_rad: float, expected_sector: int) -> None:
    spec, cost = _room()
    _put_block(spec, cost, 2.0, 2.3, -0.1, 0.1)  # a post 2 m east of the vehicle
    scan = compute_obstacle_distances(_costmap(spec, cost), (0.0, 0.0), yaw_map_rad, max_distance_m=5.0)
    blocked = [i for i, d in enumerate(scan.distances_cm) if d <= scan.max_distance_cm]
    assert expected_sector in blocked
    assert len(blocked) <= 3  # a 0.2 m post at 2 m spans ~6 deg
    assert scan.distances_cm[expected_sector] == pytest.approx(200, abs=RES_M * 100)
    assert scan.sector_center_deg(expected_sector) == pytest.approx(expected_sector * 5.0)


def test_nearest_obstacle_wins_and_close_ones_clamp_to_min_distance() -> None:
    spec, cost = _room()
    _put_block(spec, cost, 3.0, 3.2, -1.0, 1.0)
    _put_block(spec, cost, 1.0, 1.1, -0.05, 0.05)  # nearer, in the same sector
    _put_block(spec, cost, -0.1, -0.05, -0.3, 0.3)  # 5-10 cm behind: inside min_distance
    scan = compute_obstacle_distances(_costmap(spec, cost), (0.0, 0.0), 0.0, min_distance_m=0.3)
    assert scan.distances_cm[0] == pytest.approx(100, abs=RES_M * 100)
    assert scan.distances_cm[36] == 30
    assert 300 <= scan.distances_cm[3] <= 320  # 15 deg right: only the far wall (3 m / cos)


def test_inflated_cost_is_not_an_obstacle() -> None:
    spec, cost = _room()
    X, _ = spec.cell_centers_xy()
    cost[X > 1.0] = 253  # INSCRIBED_INFLATED_OBSTACLE: a soft cost, not a wall
    scan = compute_obstacle_distances(_costmap(spec, cost), (0.0, 0.0), 0.0, max_distance_m=3.0)
    assert scan.distances_cm[0] == 301


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    yaw_deg=st.floats(-180.0, 180.0),
    k=st.integers(-71, 71),
)
def test_turning_by_whole_sectors_rotates_the_array(seed: int, yaw_deg: float, k: int) -> None:
    spec, cost = _room()
    rng = np.random.default_rng(seed)
    for _ in range(6):
        x, y = rng.uniform(-4.0, 4.0, size=2)
        _put_block(spec, cost, x, x + rng.uniform(0.05, 1.0), y, y + rng.uniform(0.05, 1.0))
    cm = _costmap(spec, cost)
    xy = (0.0123, -0.0377)  # off the cell boundaries
    a = compute_obstacle_distances(cm, xy, math.radians(yaw_deg))
    b = compute_obstacle_distances(cm, xy, math.radians(yaw_deg + 5.0 * k))
    # Turning left by k sectors (ENU yaw +k*5 deg) puts every obstacle k sectors further
    # clockwise from the nose.
    assert b.distances_cm == tuple(np.roll(np.array(a.distances_cm), k))


def test_message_round_trip_through_pymavlink() -> None:
    spec, cost = _room()
    _put_block(spec, cost, 2.0, 2.3, -0.1, 0.1)
    scan = compute_obstacle_distances(_costmap(spec, cost), (0.0, 0.0), 0.0)

    class _Link:
        mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)

    buf = scan.to_message(_Link(), 123456).pack(_Link.mav)  # type: ignore[arg-type]
    decoded = mavlink.MAVLink(None).decode(bytearray(buf))
    assert decoded.get_type() == "OBSTACLE_DISTANCE"
    assert list(decoded.distances) == list(scan.distances_cm)
    assert decoded.frame == mavlink.MAV_FRAME_BODY_FRD
    assert decoded.increment_f == pytest.approx(5.0)
    assert decoded.increment == 5
    assert decoded.angle_offset == pytest.approx(0.0)
    assert (decoded.min_distance, decoded.max_distance) == (20, 800)
    assert decoded.time_usec == 123456


def test_bad_ranges_are_rejected() -> None:
    spec, cost = _room()
    with pytest.raises(ValueError, match="min_distance_m < max_distance_m"):
        compute_obstacle_distances(_costmap(spec, cost), (0.0, 0.0), 0.0, min_distance_m=5.0, max_distance_m=2.0)
    assert isinstance(ObstacleDistanceScan((0,) * 72, 0, 1, 5.0, 0.0).frame, int)


def test_input_from_px4_telemetry_uses_the_map_frame() -> None:
    import dataclasses

    from companion.mavlink.obstacle_distance import ObstacleDistanceInput
    from companion.mavlink.state import LandedState, VehicleState

    spec, cost = _room()
    _put_block(spec, cost, 2.0, 2.3, 0.9, 1.1)  # a post 2 m east of the vehicle at y = 1
    cm = _costmap(spec, cost)
    state = VehicleState(
        heartbeat_age_s=0.1, armed=True, flight_mode=None, landed_state=LandedState.IN_AIR,
        position_ned_m=(1.0, 0.0, -1.0), velocity_ned_m_s=None, position_age_s=0.0,
        attitude_rpy_rad=(0.0, 0.0, 0.0),  # NED yaw 0: facing north
        battery_v=None, battery_remaining=None, home=None, global_position=None,
        autopilot_system_status=None,
    )
    inp = ObstacleDistanceInput.from_vehicle_state(cm, state)
    assert inp is not None
    assert inp.xy_map_m == pytest.approx((0.0, 1.0)) and inp.yaw_map_rad == pytest.approx(math.pi / 2)
    scan = compute_obstacle_distances(inp.costmap, inp.xy_map_m, inp.yaw_map_rad, max_distance_m=5.0)
    assert scan.distances_cm[18] == pytest.approx(200, abs=5)  # east = 90 deg right of north
    assert ObstacleDistanceInput.from_vehicle_state(cm, dataclasses.replace(state, attitude_rpy_rad=None)) is None
