"""Vectorised plane RANSAC, floor estimation and the gravity-aligned map frame."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semmap.errors import MapError
from semmap.frames import rot_x, transform_points
from semmap.ransac import Plane, estimate_floor, fit_plane, gravity_aligned_frame


def _plane_points(rng: np.random.Generator, n: int, z: float, extent: float, noise: float) -> np.ndarray:
    xy = rng.uniform(-extent, extent, (n, 2))
    return np.column_stack([xy, z + rng.normal(0, noise, n)])


def test_fit_plane_recovers_a_tilted_plane_among_outliers() -> None:
    rng = np.random.default_rng(1)
    pts = _plane_points(rng, 400, 0.0, 1.0, 0.005)
    R = rot_x(math.radians(10.0))
    pts = pts @ R.T + [0.0, 0.0, 0.5]
    outliers = rng.uniform(-1, 1, (200, 3))
    fit = fit_plane(np.concatenate([pts, outliers]), 0.02, 200, rng)
    assert fit is not None
    n = fit.plane.normal_array
    expected = R @ [0.0, 0.0, 1.0]
    assert abs(abs(n @ expected) - 1.0) < 1e-3
    assert fit.inliers[:400].mean() > 0.95
    assert fit.inliers[400:].mean() < 0.1


def test_horizontal_constraint_prefers_the_seat_over_a_larger_backrest() -> None:
    rng = np.random.default_rng(2)
    seat = _plane_points(rng, 150, 0.45, 0.22, 0.003)
    back_yz = rng.uniform([-0.22, 0.45], [0.22, 0.95], (300, 2))
    back = np.column_stack([np.full(300, -0.22), back_yz])
    pts = np.concatenate([seat, back])
    free = fit_plane(pts, 0.01, 200, rng)
    assert free is not None and abs(free.plane.normal[2]) < 0.2  # the backrest wins unconstrained
    fit = fit_plane(pts, 0.01, 100, rng, up=np.array([0.0, 0.0, 1.0]), max_tilt_rad=math.radians(15))
    assert fit is not None
    assert fit.plane.normal[2] > 0.99
    assert fit.plane.signed_distance_m(np.array([[0.0, 0.0, 0.45]]))[0] == pytest.approx(0.0, abs=0.01)


def test_fit_plane_returns_none_without_support() -> None:
    assert fit_plane(np.zeros((2, 3)), 0.01, 10) is None
    rng = np.random.default_rng(3)
    vertical = np.column_stack([np.zeros(50), rng.uniform(0, 1, (50, 2))])
    assert fit_plane(vertical, 0.01, 50, rng, up=np.array([0, 0, 1.0]), max_tilt_rad=0.2,
                     min_inliers=20) is None


def test_floor_is_the_lowest_large_plane_not_the_biggest() -> None:
    rng = np.random.default_rng(4)
    floor = _plane_points(rng, 800, 0.0, 3.0, 0.01)
    table = _plane_points(rng, 1500, 0.75, 0.8, 0.005)
    noise_below = rng.uniform(-3, 3, (10, 3)) * [1, 1, 0.1] - [0, 0, 0.5]
    world = np.concatenate([floor, table, noise_below])
    # The world frame is a camera's: tilted by 20 degrees, the floor 1.4 m below it.
    R = rot_x(math.radians(110.0))
    T_world = np.eye(4)
    T_world[:3, :3] = R
    T_world[:3, 3] = [0.2, 1.4, -0.3]
    pts = transform_points(T_world, world)
    up_world = R @ [0.0, 0.0, 1.0]
    fit = estimate_floor(pts, up_hint=np.array([0.0, -1.0, 0.0]), rng=rng)
    assert fit.plane.normal_array @ up_world > 0.999
    T_map_world = gravity_aligned_frame(fit.plane)
    z_floor = transform_points(T_map_world, pts[:800])[:, 2]
    z_table = transform_points(T_map_world, pts[800:2300])[:, 2]
    assert abs(np.median(z_floor)) < 0.01
    assert np.median(z_table) == pytest.approx(0.75, abs=0.01)


def test_floor_estimation_fails_clearly_without_a_horizontal_plane() -> None:
    rng = np.random.default_rng(5)
    wall = np.column_stack([rng.uniform(0, 3, 500), rng.uniform(0, 3, 500), np.zeros(500)])
    with pytest.raises(MapError, match="floor"):
        estimate_floor(wall, up_hint=np.array([1.0, 0.0, 0.0]), max_tilt_rad=math.radians(20))


def test_horizontal_plane_helper() -> None:
    p = Plane.horizontal(0.7)
    assert p.signed_distance_m(np.array([[1.0, 2.0, 1.0]]))[0] == pytest.approx(0.3)
    assert p.tilt_rad(np.array([0, 0, 1.0])) == pytest.approx(0.0)
