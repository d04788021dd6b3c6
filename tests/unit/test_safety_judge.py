"""The safety judge (bench/_judge.py): collisions with the vertical margin, success, clearance."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bench._judge import judge_flight
from companion.errors import SimulationError
from companion.sim.groundtruth import colliding_owners
from companion.sim.world import Box, FurnitureObject, Room

R, H, MARGIN = 0.25, 0.15, 0.10


def _room() -> Room:
    """A 6 x 4 m room (one wall along y = 0) with a desk at (3, 2): 1.2 x 0.8 m, top 0.72-0.75 m,
    legs 0.325 m either side of y = 2 (a vehicle of radius 0.25 m passes between them)."""
    L, W, top, t = 1.2, 0.8, 0.75, 0.03
    parts = [Box((3.0, 2.0, top - t / 2), (L, W, t))]
    parts += [Box((3.0 + sx * (L / 2 - 0.05), 2.0 + sy * (W / 2 - 0.05), (top - t) / 2), (0.05, 0.05, top - t))
              for sx in (-1, 1) for sy in (-1, 1)]
    desk = FurnitureObject(5, "desk", (3.0, 2.0), 0.0, (L, W, top), tuple(parts), (160, 120, 80))
    wall = Box((3.0, -0.06, 1.3), (6.0, 0.12, 2.6))
    return Room(1, 6.0, 4.0, 2.6, (wall,), (), (desk,))


def _line(z_m: float, y_m: float = 2.0, x0: float = 0.5, x1: float = 5.5, speed_m_s: float = 1.0
          ) -> tuple[np.ndarray, np.ndarray]:
    x = np.arange(x0, x1 + 1e-9, 0.05)
    xyz = np.column_stack([x, np.full_like(x, y_m), np.full_like(x, z_m)])
    return xyz, (x - x0) / speed_m_s


def _judge(xyz: np.ndarray, t: np.ndarray, goal: tuple[float, float] = (5.5, 2.0), limit_s: float = 30.0):  # noqa: ANN202
    return judge_flight(_room(), xyz, t, goal, vehicle_radius_m=R, vehicle_height_m=H,
                        vertical_margin_m=MARGIN, acceptance_m=0.3, time_limit_s=limit_s)


def test_grazing_under_a_table_top_is_a_collision_with_the_margin() -> None:
    # At 0.6 m the airframe (0.525..0.675 m) clears the top's underside (0.72 m) by 4.5 cm,
    # less than the 10 cm vertical margin: the metric-only failure the bench counts.
    v = _judge(*_line(0.6))
    assert v.collided and not v.collided_exact
    assert v.hit_object_ids == (5,)
    assert v.min_clearance_m < 0.0


def test_flying_into_the_top_is_an_exact_collision() -> None:
    v = _judge(*_line(0.72))
    assert v.collided and v.collided_exact


def test_flying_over_a_low_table_is_safe() -> None:
    v = _judge(*_line(1.5))
    assert not v.collided and not v.collided_exact
    assert v.min_object_clearance_m == math.inf  # nothing at that height but the wall
    assert v.min_clearance_m == pytest.approx(2.0 - R, abs=0.03)  # the wall along y = 0
    assert v.reached and v.success
    # Reached on entering the 0.3 m acceptance radius, 4.7 m along at 1 m/s.
    assert v.path_length_m == pytest.approx(4.7, abs=0.01)
    assert v.time_s == pytest.approx(4.7, abs=0.01)


def test_passing_beside_the_desk_reports_the_side_clearance() -> None:
    # The desk spans y 1.6..2.4; a pass at y = 2.9 keeps 0.5 m centre distance.
    v = _judge(*_line(0.6, y_m=2.9), goal=(5.5, 2.9))
    assert not v.collided
    assert v.min_object_clearance_m == pytest.approx(0.5 - R, abs=0.01)


def test_success_needs_the_goal_within_the_time_limit() -> None:
    xyz, t = _line(1.5)
    assert not _judge(xyz, t, limit_s=4.0).success  # reached after 4.7 s
    assert _judge(xyz, t, limit_s=4.0).reached
    short = _judge(xyz[:50], t[:50])  # stops 2.5 m short
    assert not short.reached and not short.success
    assert short.time_s == pytest.approx(t[49])


def test_on_the_floor_at_the_goal_does_not_count() -> None:
    xyz, t = _line(0.05)
    assert not _judge(xyz, t).reached


def test_bad_input_is_refused() -> None:
    with pytest.raises(SimulationError, match="stamps"):
        _judge(np.zeros((3, 3)), np.zeros(2))
    with pytest.raises(SimulationError, match="finite"):
        _judge(np.full((2, 3), np.nan), np.zeros(2))


@settings(max_examples=40, deadline=None)
@given(z=st.floats(0.1, 2.0), y=st.floats(0.3, 3.7))
def test_collided_iff_negative_clearance(z: float, y: float) -> None:
    xyz, t = _line(z, y_m=y)
    v = _judge(xyz, t, goal=(5.5, y))
    assert v.collided == (v.min_clearance_m < 0.0)
    assert v.collided == (v.collision_points > 0)
    assert v.collided == bool(colliding_owners(_room(), xyz, R, H + 2 * MARGIN))
    assert not v.collided_exact or v.collided  # exact collisions are a subset
