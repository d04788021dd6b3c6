"""The floor of a view from gravity: its height only, and no floor rather than a guess."""

from __future__ import annotations

import numpy as np

from semmap.floor import view_floor_height_m
from tests.unit.test_geometry import TABLE_BOXES, K, camera_pose, render

RANGE_M = (0.3, 8.0)


def _floor(height_m: float) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    return ((-10.0, -10.0, -1.0), (10.0, 10.0, height_m))


def test_the_floor_height_is_the_lowest_large_layer_not_the_larger_table_top() -> None:
    T = camera_pose(1.6, 1.0, 1.5, 0.0, 35.0)
    # A top larger than the visible floor, and the floor 6 cm above the map's zero.
    top = [((1.7, -1.5, 0.09), (4.5, 3.5, 0.12))]
    depth = render(top + [_floor(0.06)], T)
    assert view_floor_height_m(depth, K, T, RANGE_M) is not None
    assert abs(view_floor_height_m(depth, K, T, RANGE_M) - 0.06) < 0.005  # type: ignore[operator]


def test_noisy_floor_depth_gives_the_floors_middle() -> None:
    T = camera_pose(1.0, 1.0, 1.5, 0.0, 30.0)
    depth = render(TABLE_BOXES + [_floor(0.0)], T)
    rng = np.random.default_rng(3)
    noisy = (depth * (1.0 + rng.normal(0.0, 0.01, depth.shape))).astype(np.float32)
    h = view_floor_height_m(noisy, K, T, RANGE_M)
    assert h is not None and abs(h) < 0.01


def test_a_view_without_floor_has_none() -> None:
    T = camera_pose(1.0, 1.0, 1.5, 0.0, 60.0)
    # Looking down onto a wide bed-like top at 0.5 m: nothing near the floor height.
    depth = render([((-5.0, -5.0, 0.0), (8.0, 8.0, 0.5))], T)
    assert view_floor_height_m(depth, K, T, RANGE_M) is None
    # A camera facing a wall sees no floor either.
    wall = render([((2.0, -5.0, 0.5), (2.2, 5.0, 3.0))], camera_pose(1.0, 1.0, 1.5, 0.0, 0.0))
    assert view_floor_height_m(wall, K, camera_pose(1.0, 1.0, 1.5, 0.0, 0.0), RANGE_M) is None
