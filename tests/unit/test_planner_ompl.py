"""The OMPL backend on its own: every planner returns a free path; the informed box is sound."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planner.cspace import build_cspace
from planner.ompl_backend import PLANNERS, informed_bounds, ompl_solve
from semmap.costmap import FREE_SPACE, Costmap, ObjectFootprint, VerticalBand
from semmap.errors import PlanningError
from semmap.grid import GridSpec
from semmap.inflation import InflationParams
from semmap.layers import paint_objects

SPEC = GridSpec(0.05, (0.0, 0.0), (60, 100))
BAND = VerticalBand.for_altitude(0.5, 0.15, 0.1)


def _cspace():
    wall = np.array([[2.3, 0.0], [2.7, 0.0], [2.7, 2.2], [2.3, 2.2]])
    base = Costmap(SPEC, np.full(SPEC.shape_rc, FREE_SPACE, np.uint8), BAND)
    cm = paint_objects(base, [ObjectFootprint(1, "desk", wall, 0.0, 0.75)], BAND)
    return build_cspace(cm, InflationParams(vehicle_radius_m=0.2))


@pytest.mark.parametrize("algorithm", sorted(PLANNERS))
@pytest.mark.parametrize("weight", [0.0, 0.5])
def test_every_planner_finds_a_free_path_around_the_wall(algorithm: str, weight: float) -> None:
    cs = _cspace()
    path = ompl_solve(cs, np.array([1.0, 1.0]), np.array([4.0, 1.0]), algorithm, 0.3, weight)
    assert path is not None
    assert cs.path_free(path)
    np.testing.assert_allclose(path[0], [1.0, 1.0])
    np.testing.assert_allclose(path[-1], [4.0, 1.0])
    assert path[:, 1].max() > 2.2  # went around the top of the wall


def test_unknown_planner_is_an_error() -> None:
    with pytest.raises(PlanningError, match="unknown planner"):
        ompl_solve(_cspace(), np.array([1.0, 1.0]), np.array([4.0, 1.0]), "prm", 0.1, 0.0)


@settings(max_examples=50, deadline=None)
@given(st.floats(0.5, 4.5), st.floats(0.5, 2.5), st.floats(0.5, 4.5), st.floats(0.5, 2.5),
       st.floats(1.0, 2.0), st.floats(0.0, 2 * math.pi))
def test_informed_box_contains_the_ellipse(sx: float, sy: float, gx: float, gy: float,
                                           factor: float, angle: float) -> None:
    cs = _cspace()
    s, g = np.array([sx, sy]), np.array([gx, gy])
    d = float(np.linalg.norm(g - s))
    bound = max(d, 1e-3) * factor
    x0, y0, x1, y1 = informed_bounds(cs, s, g, bound)
    # A point with |p - s| + |p - g| = bound (on the ellipse), reached along ``angle`` from the centre.
    c = 0.5 * (s + g)
    u = np.array([math.cos(angle), math.sin(angle)])
    lo, hi = 0.0, bound
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        p = c + mid * u
        if np.linalg.norm(p - s) + np.linalg.norm(p - g) < bound:
            lo = mid
        else:
            hi = mid
    p = c + lo * u
    ex0, ey0, ex1, ey1 = cs.spec.extent_xy_m
    if ex0 <= p[0] <= ex1 and ey0 <= p[1] <= ey1:
        assert x0 - 1e-6 <= p[0] <= x1 + 1e-6 and y0 - 1e-6 <= p[1] <= y1 + 1e-6
