"""The Cartographer-style probability grid: tables, clamping, updates, growth."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from semmap.errors import MapError
from semmap.grid import GridSpec
from semmap.occupancy import (
    MAX_VALUE,
    MIN_VALUE,
    UNKNOWN_VALUE,
    Bounds,
    ProbabilityGrid,
    ProbabilityTables,
    odds,
    probability_from_odds,
)

TABLES = ProbabilityTables(0.55, 0.49, 0.12, 0.97)


def small_grid(fixed: bool = False) -> ProbabilityGrid:
    return ProbabilityGrid(GridSpec(0.1, (0.0, 0.0), (20, 30)), TABLES, fixed_size=fixed, grow_chunk_m=1.0)


@given(st.floats(0.01, 0.99))
def test_odds_round_trip(p: float) -> None:
    assert float(probability_from_odds(odds(p))) == pytest.approx(p, abs=1e-12)


@given(st.floats(0.12, 0.97))
def test_value_round_trip_within_quantisation(p: float) -> None:
    v = TABLES.probability_to_value(p)
    assert MIN_VALUE <= int(v) <= MAX_VALUE
    step = (0.97 - 0.12) / (MAX_VALUE - MIN_VALUE)
    assert float(TABLES.value_to_probability[int(v)]) == pytest.approx(p, abs=step)


def test_first_observation_lands_on_hit_and_miss_probability() -> None:
    p = TABLES.value_to_probability
    assert p[TABLES.hit_table[UNKNOWN_VALUE]] == pytest.approx(0.55, abs=1e-4)
    assert p[TABLES.miss_table[UNKNOWN_VALUE]] == pytest.approx(0.49, abs=1e-4)


def test_tables_move_probability_the_right_way_and_clamp() -> None:
    values = np.arange(MIN_VALUE, MAX_VALUE + 1)
    assert np.all(TABLES.hit_table[values] >= values)
    assert np.all(TABLES.miss_table[values] <= values)
    assert TABLES.hit_table[MAX_VALUE] == MAX_VALUE
    assert TABLES.miss_table[MIN_VALUE] == MIN_VALUE
    assert TABLES.hit_table.min() >= MIN_VALUE and TABLES.miss_table.min() >= MIN_VALUE


def test_one_hit_multiplies_the_odds() -> None:
    v = int(TABLES.probability_to_value(0.7))
    after = float(TABLES.value_to_probability[TABLES.hit_table[v]])
    expected = float(probability_from_odds(odds(0.7) * odds(0.55)))
    assert after == pytest.approx(expected, abs=1e-4)


def test_repeated_hits_and_misses_clamp() -> None:
    g = small_grid()
    cell = np.array([[5, 5]])
    none = np.zeros((0, 2), int)
    for _ in range(200):
        g.apply(cell, none)
    assert g.probability()[5, 5] == pytest.approx(0.97, abs=1e-4)
    for _ in range(500):
        g.apply(none, cell)
    assert g.probability()[5, 5] == pytest.approx(0.12, abs=1e-4)


def test_each_cell_updates_once_per_scan_and_hits_win() -> None:
    g = small_grid()
    hits = np.array([[1, 1], [1, 1], [1, 1]])
    misses = np.array([[1, 1], [2, 2], [2, 2], [2, 2]])
    bounds = g.apply(hits, misses)
    p = g.probability()
    assert p[1, 1] == pytest.approx(0.55, abs=1e-4)
    assert p[2, 2] == pytest.approx(0.49, abs=1e-4)
    assert np.isnan(p[0, 0])
    assert bounds == Bounds(1, 1, 3, 3)
    assert g.known.sum() == 2


def test_cells_outside_are_ignored() -> None:
    g = small_grid(fixed=True)
    bounds = g.apply(np.array([[-1, 0], [0, 99]]), np.array([[25, 3]]))
    assert bounds.is_empty and not g.known.any()


def test_probability_u8_and_known_mask() -> None:
    g = small_grid()
    g.apply(np.array([[0, 0]]), np.array([[0, 1]]))
    u8, known = g.probability_u8()
    assert u8.dtype == np.uint8 and known.dtype == bool
    assert u8[0, 0] == round(0.55 * 255) and u8[0, 1] == round(0.49 * 255)
    assert known.sum() == 2


def test_grow_keeps_cells_at_their_map_position() -> None:
    g = small_grid()
    g.apply(np.array([[3, 4]]), np.zeros((0, 2), int))
    xy = g.spec.center_of(np.array([[3, 4]]))
    shift = g.ensure_contains(-0.55, -0.2, 3.5, 2.5)
    assert shift == (10, 10)  # 1 m chunks at 0.1 m
    assert g.spec.origin_xy_m == pytest.approx((-1.0, -1.0))
    x0, y0, x1, y1 = g.spec.extent_xy_m
    assert x0 <= -0.55 and y0 <= -0.2 and x1 >= 3.5 and y1 >= 2.5
    assert g.probability_at_xy(xy)[0] == pytest.approx(0.55, abs=1e-4)
    assert g.known.sum() == 1


def test_fixed_grid_does_not_grow() -> None:
    g = small_grid(fixed=True)
    assert g.ensure_contains(-5, -5, 50, 50) == (0, 0)
    assert g.spec.shape_rc == (20, 30)


def test_insert_scan_marks_free_fan_and_hits() -> None:
    g = ProbabilityGrid(GridSpec(0.05, (-1.0, -1.0), (40, 40)), TABLES, grow_chunk_m=1.0)
    # Five rays from the origin fanning out over +-10 degrees, ending on a wall at x = 1.5.
    ang = np.radians(np.linspace(-10, 10, 21))
    hits = np.stack([np.full_like(ang, 1.5), 1.5 * np.tan(ang)], axis=1)
    origin = np.zeros(2)
    bounds = g.insert_scan(origin, np.zeros_like(hits), hits, hits, np.ones(21, bool), np.ones(21, bool))
    assert g.spec.extent_xy_m[2] >= 1.5  # grew to hold the wall
    p_wall = g.probability_at_xy(hits)
    assert np.all(p_wall > 0.5)
    free_pts = np.array([[0.5, 0.0], [1.0, 0.1], [1.3, -0.2]])
    assert np.all(g.probability_at_xy(free_pts) < 0.5)
    behind = np.array([[1.8, 0.0], [0.5, 0.6], [-0.3, 0.0]])
    assert np.all(np.isnan(g.probability_at_xy(behind)))
    assert not bounds.is_empty


def test_insert_scan_skips_invalid_rays() -> None:
    g = small_grid()
    far = np.array([[1.0, 1.0], [1.5, 1.0], [2.0, 1.0]])
    valid = np.array([False, False, False])
    assert g.insert_scan(np.array([0.5, 0.5]), far * 0 + 0.5, far, far, valid, valid).is_empty
    assert not g.known.any()


def test_copy_is_independent() -> None:
    g = small_grid()
    c = g.copy()
    c.apply(np.array([[0, 0]]), np.zeros((0, 2), int))
    assert not g.known.any() and c.known.any()


def test_bad_parameters_are_rejected() -> None:
    with pytest.raises(MapError, match="hit_probability"):
        ProbabilityTables(hit_probability=0.4)
    with pytest.raises(MapError, match="min_probability"):
        ProbabilityTables(min_probability=0.6, max_probability=0.55)
    g = small_grid()
    with pytest.raises(MapError, match="uint16"):
        g.set_values(np.zeros((3, 3), np.uint8))
