"""Configuration space on the map's inflation layer: the map-costed objects (altitude rule,
margins), the vehicle radius, conservative clearance, window updates."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from planner.cspace import build_cspace, update_cspace
from semmap.costmap import (
    FREE_SPACE,
    LETHAL_OBSTACLE,
    NO_INFORMATION,
    Costmap,
    ObjectFootprint,
    VerticalBand,
)
from semmap.errors import ConfigError
from semmap.grid import GridSpec
from semmap.inflation import InflationParams
from semmap.layers import cost_decay, paint_objects

SPEC = GridSpec(0.05, (0.0, 0.0), (80, 100))  # 5 m x 4 m


def rect(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)


def empty_costmap(band: VerticalBand) -> Costmap:
    return Costmap(SPEC, np.full(SPEC.shape_rc, FREE_SPACE, dtype=np.uint8), band)


def coffee_table() -> ObjectFootprint:
    return ObjectFootprint(1, "coffee_table", rect(2.0, 1.5, 3.0, 2.1), z_min_m=0.0, z_max_m=0.45)


def desk() -> ObjectFootprint:
    return ObjectFootprint(2, "desk", rect(2.0, 1.5, 3.4, 2.2), z_min_m=0.0, z_max_m=0.75)


def test_coffee_table_does_not_block_at_1_5_m() -> None:
    band = VerticalBand.for_altitude(1.5, 0.15, 0.1)
    cm = paint_objects(empty_costmap(band), [coffee_table()], band)
    assert not cm.lethal.any()


def test_desk_blocks_its_whole_footprint_at_0_5_m() -> None:
    band = VerticalBand.for_altitude(0.5, 0.15, 0.1)
    fp = desk()
    cm = paint_objects(empty_costmap(band), [fp], band)
    inside = fp.mask(SPEC)
    assert cm.lethal[inside].all()
    # The space between the legs (the centre of the footprint) is blocked too.
    assert bool(cm.lethal[SPEC.cell_of(np.array([[2.7, 1.85]]))[0][0], SPEC.cell_of(np.array([[2.7, 1.85]]))[0][1]])


def test_unconfirmed_objects_are_a_soft_cost_not_an_obstacle() -> None:
    band = VerticalBand.for_altitude(0.5, 0.15, 0.1)
    fp = ObjectFootprint(3, "desk", rect(2.0, 1.5, 3.4, 2.2), 0.0, 0.75, existence=0.2)
    cm = paint_objects(empty_costmap(band), [fp], band, existence_confirm=0.5)
    assert not cm.lethal.any()
    cs = build_cspace(cm, InflationParams(vehicle_radius_m=0.25))
    centre = np.array([[2.7, 1.85]])
    assert cs.is_free(centre)[0] and cs.cost_at(centre)[0] == pytest.approx(0.2, abs=0.01)


def test_free_respects_radius_conservatively() -> None:
    band = VerticalBand.for_altitude(0.5, 0.15, 0.1)
    cm = paint_objects(empty_costmap(band), [desk()], band)
    cs = build_cspace(cm, InflationParams(vehicle_radius_m=0.3))
    # Points closer than the radius to the desk's edge (x = 2.0) are never free.
    assert not cs.is_free(np.array([[1.75, 1.8]]))[0]
    assert not cs.is_free(np.array([[1.71, 1.8]]))[0]
    # Far away is free.
    assert cs.is_free(np.array([[0.8, 1.8]]))[0]
    # Outside the map is never free.
    assert not cs.is_free(np.array([[-0.1, 1.0]]))[0]


@settings(max_examples=60, deadline=None)
@given(st.floats(0.0, 5.0), st.floats(0.0, 4.0))
def test_clearance_is_a_lower_bound_on_true_distance(x: float, y: float) -> None:
    band = VerticalBand.for_altitude(0.5, 0.15, 0.1)
    x0, y0, x1, y1 = 2.0, 1.5, 3.4, 2.2
    cm = paint_objects(empty_costmap(band), [ObjectFootprint(1, "desk", rect(x0, y0, x1, y1), 0.0, 0.75)], band)
    cs = build_cspace(cm, InflationParams(vehicle_radius_m=0.3))
    clr = float(cs.clearance_at(np.array([[x, y]]))[0])
    true = float(np.hypot(max(x0 - x, 0.0, x - x1), max(y0 - y, 0.0, y - y1)))
    assert clr <= true + 1e-9


def test_segment_through_obstacle_is_not_free() -> None:
    band = VerticalBand.for_altitude(0.5, 0.15, 0.1)
    cm = paint_objects(empty_costmap(band), [desk()], band)
    cs = build_cspace(cm, InflationParams(vehicle_radius_m=0.25))
    assert not cs.segment_free((0.5, 1.85), (4.5, 1.85))
    assert cs.segment_free((0.5, 0.6), (4.5, 0.6))
    assert not cs.segment_free((0.5, 0.6), (5.5, 0.6))  # leaves the map


def test_object_margin_grows_blocked_area() -> None:
    band = VerticalBand.for_altitude(0.5, 0.15, 0.1)
    plain = paint_objects(empty_costmap(band), [desk()], band)
    fp = ObjectFootprint(2, "desk", rect(2.0, 1.5, 3.4, 2.2), 0.0, 0.75, margin_m=0.3)
    with_margin = paint_objects(empty_costmap(band), [fp], band)
    a = build_cspace(plain, InflationParams(vehicle_radius_m=0.2))
    b = build_cspace(with_margin, InflationParams(vehicle_radius_m=0.2))
    assert b.layer.blocked.sum() > a.layer.blocked.sum()
    assert a.is_free(np.array([[1.5, 1.85]]))[0] and not b.is_free(np.array([[1.5, 1.85]]))[0]


def test_unknown_space_forbidden_only_at_full_cost() -> None:
    band = VerticalBand.for_altitude(0.5, 0.15, 0.1)
    cost = np.full(SPEC.shape_rc, FREE_SPACE, dtype=np.uint8)
    cost[:, 60:] = NO_INFORMATION
    cm = Costmap(SPEC, cost, band)
    allowed = build_cspace(cm, InflationParams(vehicle_radius_m=0.2, unknown_cost=0.5))
    forbidden = build_cspace(cm, InflationParams(vehicle_radius_m=0.2, unknown_cost=1.0))
    p = np.array([[4.0, 2.0]])
    assert allowed.is_free(p)[0] and allowed.cost_at(p)[0] >= 0.5
    assert not forbidden.is_free(p)[0]


def test_geofence_blocks_outside() -> None:
    band = VerticalBand.for_altitude(0.5, 0.15, 0.1)
    cs = build_cspace(empty_costmap(band), InflationParams(vehicle_radius_m=0.2, geofence_xy_m=(0.0, 0.0, 3.0, 4.0)))
    assert cs.is_free(np.array([[2.0, 2.0]]))[0]
    assert not cs.is_free(np.array([[2.9, 2.0]]))[0]  # within the radius of the fence
    assert not cs.is_free(np.array([[4.0, 2.0]]))[0]


@settings(max_examples=15, deadline=None)
@given(st.floats(0.5, 4.0), st.floats(0.5, 3.0), st.floats(0.1, 0.8), st.floats(0.1, 0.8),
       st.sampled_from([0.0, 0.1]))
def test_window_update_equals_full_rebuild(x: float, y: float, w: float, h: float, tracking_m: float) -> None:
    band = VerticalBand.for_altitude(0.5, 0.15, 0.1)
    params = InflationParams(vehicle_radius_m=0.25, tracking_margin_m=tracking_m)
    before = paint_objects(empty_costmap(band), [desk()], band)
    new_obj = ObjectFootprint(9, "chair", rect(x, y, x + w, y + h), 0.0, 0.9)
    after = paint_objects(empty_costmap(band), [desk(), new_obj], band)
    # Unclassified occupancy appears too (it keeps the tracking margin, the chair its class's).
    r, c = SPEC.cell_of(np.array([[min(x + 0.5, 4.9), y]]))[0]
    occupied = after.cost.copy()
    occupied[r:r + 3, c:c + 3] = LETHAL_OBSTACLE
    after = Costmap(SPEC, occupied, band)
    cs0 = build_cspace(before, params, version=1)
    updated, window = update_cspace(cs0, after, version=2)
    full = build_cspace(after, params, version=2)
    assert (window is None) == bool(np.array_equal(before.cost, after.cost))
    np.testing.assert_allclose(updated.clearance_m, full.clearance_m, atol=1e-5)
    np.testing.assert_array_equal(updated.free, full.free)
    np.testing.assert_allclose(updated.cost, full.cost, atol=1e-6)
    assert updated.version == 2


def test_update_without_change_keeps_fields() -> None:
    band = VerticalBand.for_altitude(0.5, 0.15, 0.1)
    cm = paint_objects(empty_costmap(band), [desk()], band)
    cs0 = build_cspace(cm, InflationParams(vehicle_radius_m=0.25))
    cs1, window = update_cspace(cs0, cm, version=5)
    assert window is None and cs1.version == 5 and cs1.free is cs0.free


def test_lethal_cells_are_never_free() -> None:
    band = VerticalBand.for_altitude(0.5, 0.15, 0.1)
    cost = np.zeros(SPEC.shape_rc, dtype=np.uint8)
    cost[40, 50] = LETHAL_OBSTACLE
    cs = build_cspace(Costmap(SPEC, cost, band), InflationParams(vehicle_radius_m=0.1))
    assert not cs.free[40, 50] and cs.free[40, 70]


def test_inscribed_cells_are_blocked_and_soft_costs_scale() -> None:
    from semmap.costmap import INSCRIBED_INFLATED_OBSTACLE, MAX_NON_OBSTACLE

    band = VerticalBand.for_altitude(0.5, 0.15, 0.1)
    cost = np.zeros(SPEC.shape_rc, dtype=np.uint8)
    cost[40, 20] = INSCRIBED_INFLATED_OBSTACLE
    cost[40, 80] = MAX_NON_OBSTACLE
    cs = build_cspace(Costmap(SPEC, cost, band, clearance_decay_m=0.05), InflationParams(vehicle_radius_m=0.1))
    assert cs.layer.blocked[40, 20] and not cs.free[40, 20]
    assert not cs.layer.blocked[40, 80] and cs.free[40, 80] and cs.cost[40, 80] == pytest.approx(1.0)


@settings(max_examples=20, deadline=None)
@given(st.floats(0.3, 4.0), st.floats(0.3, 3.0), st.floats(0.05, 1.0), st.floats(0.0, 0.6))
@example(1.0, 1.0, 1.0, 0.45)  # cells exactly 0.45 m off were left outside the margin by rounding
def test_object_margin_equals_distance_to_footprint(x: float, y: float, size: float, margin: float) -> None:
    from scipy import ndimage

    band = VerticalBand.for_altitude(0.5, 0.15, 0.1)
    fp = ObjectFootprint(1, "chair", rect(x, y, x + size, y + size * 0.7), 0.0, 0.9, margin_m=margin)
    cm = paint_objects(empty_costmap(band), [fp], band)
    cs = build_cspace(cm, InflationParams(vehicle_radius_m=0.2))
    dist = ndimage.distance_transform_edt(~cm.lethal, sampling=SPEC.resolution_m)
    # A cell exactly at the margin (rounding either way) is blocked: the safe side.
    np.testing.assert_array_equal(cs.layer.blocked, dist <= margin + 1e-9)


def test_the_planner_adds_no_object_cost_of_its_own() -> None:
    # The map's layers are the one owner of object cost: a footprint the costmap shows
    # lethal without a painted margin gets no margin from the planner.
    band = VerticalBand.for_altitude(0.5, 0.15, 0.1)
    fp = ObjectFootprint(2, "desk", rect(2.0, 1.5, 3.4, 2.2), 0.0, 0.75, margin_m=0.3)
    cost = np.full(SPEC.shape_rc, FREE_SPACE, dtype=np.uint8)
    cost[fp.mask(SPEC)] = LETHAL_OBSTACLE
    cs = build_cspace(Costmap(SPEC, cost, band, objects=(fp,)), InflationParams(vehicle_radius_m=0.2))
    np.testing.assert_array_equal(cs.layer.blocked, cost == LETHAL_OBSTACLE)


@pytest.mark.parametrize("decay_m", [0.05, 0.15, 0.4])
def test_proximity_cost_decays_with_the_costmaps_decay(decay_m: float) -> None:
    band = VerticalBand.for_altitude(0.5, 0.15, 0.1)
    cm = paint_objects(Costmap(SPEC, np.zeros(SPEC.shape_rc, np.uint8), band, clearance_decay_m=decay_m),
                       [desk()], band)
    cs = build_cspace(cm, InflationParams(vehicle_radius_m=0.2))
    assert cs.layer.clearance_decay_m == decay_m
    p = np.array([[1.2, 1.85]])  # 0.8 m left of the desk
    beyond = float(cs.clearance_at(p)[0]) - cs.free_threshold_m
    assert cs.cost_at(p)[0] == pytest.approx(float(cost_decay(beyond, decay_m)), rel=1e-5)


def test_a_new_decay_rebuilds_the_whole_space() -> None:
    band = VerticalBand.for_altitude(0.5, 0.15, 0.1)
    cm = paint_objects(empty_costmap(band), [desk()], band)
    cs0 = build_cspace(cm, InflationParams(vehicle_radius_m=0.25))
    slower = paint_objects(Costmap(SPEC, cm.cost * 0, band, clearance_decay_m=0.4), [desk()], band)
    cs1, window = update_cspace(cs0, slower, version=1)
    full = build_cspace(slower, InflationParams(vehicle_radius_m=0.25), version=1)
    assert window == SPEC.bounds
    np.testing.assert_allclose(cs1.cost, full.cost)


def _wall_costmap(band: VerticalBand) -> Costmap:
    """Unclassified occupancy (a wall or clutter, no class margin) along x = 2.0..2.1 m."""
    cost = np.full(SPEC.shape_rc, FREE_SPACE, dtype=np.uint8)
    cost[:, 40:42] = LETHAL_OBSTACLE
    return Costmap(SPEC, cost, band)


def test_px4_sitl_seed1_cabinet_graze_unclassified_obstacles_keep_the_tracking_margin() -> None:
    # PX4 flew a path that kept only the vehicle radius from a cabinet held as occupancy, a
    # few cm inside it: a cell just beyond radius + a quarter cell must not be free any more.
    band = VerticalBand.for_altitude(0.5, 0.15, 0.1)
    cm = _wall_costmap(band)
    radius_only = build_cspace(cm, InflationParams(vehicle_radius_m=0.25))
    tracked = build_cspace(cm, InflationParams(vehicle_radius_m=0.25, tracking_margin_m=0.1))
    # Cell centre x = 1.625 m: 0.375 m from the wall face, 0.35 to the nearest blocked centre
    # minus a cell diagonal bound 0.279 m, enough for the radius alone.
    near = np.array([[1.625, 2.0]])
    assert radius_only.is_free(near)[0]
    assert not tracked.is_free(near)[0]
    # Every free point of the tracked space keeps radius + margin from the wall's true face.
    rows, cols = np.nonzero(tracked.free)
    x_m = (cols + 0.5) * SPEC.resolution_m
    gap_m = np.where(x_m < 2.0, 2.0 - x_m, x_m - 2.1)
    assert gap_m.min() >= 0.25 + 0.1


def test_tracking_margin_counts_in_thresholds_and_escape() -> None:
    band = VerticalBand.for_altitude(0.5, 0.15, 0.1)
    cs = build_cspace(_wall_costmap(band), InflationParams(vehicle_radius_m=0.25, tracking_margin_m=0.1))
    assert cs.free_threshold_m == pytest.approx(0.25 + SPEC.resolution_m / 4)
    esc = cs.escape_point(np.array([1.9, 2.0]))
    assert esc is not None and 2.0 - esc[0] >= 0.35


def test_negative_tracking_margin_is_refused() -> None:
    with pytest.raises(ConfigError, match="tracking_margin_m"):
        InflationParams(vehicle_radius_m=0.25, tracking_margin_m=-0.1)
    with pytest.raises(ConfigError, match="vehicle_radius_m"):
        InflationParams(vehicle_radius_m=0.0)


def test_a_class_margin_wider_than_the_tracking_margin_is_not_widened() -> None:
    # The tracking margin is for obstacles without a class margin: an object's own margin
    # (0.2 m for a coffee table) already keeps the vehicle that far off.
    band = VerticalBand.for_altitude(0.3, 0.15, 0.1)
    cm = paint_objects(empty_costmap(band), [coffee_table()], band, class_margins_m={"coffee_table": 0.2})
    plain = build_cspace(cm, InflationParams(vehicle_radius_m=0.25))
    tracked = build_cspace(cm, InflationParams(vehicle_radius_m=0.25, tracking_margin_m=0.1))
    assert np.array_equal(plain.free, tracked.free)
    cap = plain.layer.influence_m  # the tracked space looks that much further before it caps
    out = ~plain.layer.blocked
    assert np.allclose(np.minimum(tracked.clearance_m, cap)[out], plain.clearance_m[out])
    # With no class margin the same table is kept the tracking margin further away.
    bare = paint_objects(empty_costmap(band), [coffee_table()], band, class_margins_m={"coffee_table": 0.0})
    assert build_cspace(bare, InflationParams(vehicle_radius_m=0.25, tracking_margin_m=0.1)).free.sum() < \
        build_cspace(bare, InflationParams(vehicle_radius_m=0.25)).free.sum()
