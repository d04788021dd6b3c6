"""Semantic layers and their combination: altitude rule, margins, freshness, rules."""

from __future__ import annotations

import numpy as np
import pytest

from semmap.costmap import (
    FREE_SPACE,
    INSCRIBED_INFLATED_OBSTACLE,
    LETHAL_OBSTACLE,
    NO_INFORMATION,
    Costmap,
    ObjectFootprint,
    VerticalBand,
)
from semmap.errors import MapError
from semmap.grid import GridSpec
from semmap.layers import (
    COMBINE_RULES,
    LayeredCostmap,
    combine_maximum,
    combine_overwrite,
    existence_cost,
    paint_objects,
)
from semmap.occupancy import Bounds, ProbabilityGrid

CLASSES = ["chair", "coffee_table", "desk"]
TABLE = np.array([[1.0, 1.0], [2.0, 1.0], [2.0, 1.6], [1.0, 1.6]])


def band_at(altitude_m: float) -> VerticalBand:
    return VerticalBand.for_altitude(altitude_m, vehicle_height_m=0.15, margin_m=0.1)


def coffee_table(existence: float = 0.9, margin_m: float | None = 0.2, oid: int = 1) -> ObjectFootprint:
    return ObjectFootprint(oid, "coffee_table", TABLE, 0.0, 0.45, existence=existence, margin_m=margin_m)


def stack(shape=(80, 80), **kw) -> LayeredCostmap:  # type: ignore[no-untyped-def]
    grid = ProbabilityGrid(GridSpec(0.05, (0.0, 0.0), shape), fixed_size=True)
    return LayeredCostmap(grid, CLASSES, **kw)


def cost_at(lc: LayeredCostmap, band: VerticalBand, x: float, y: float) -> int:
    return int(lc.costmap(band).cost_at_xy(np.array([[x, y]]))[0])


def test_coffee_table_blocks_at_0_4_m_but_not_at_1_5_m() -> None:
    lc = stack()
    lc.update_objects([coffee_table()], stamp_s=1.0)
    centre = (1.5, 1.3)  # under the table top, between the legs
    assert cost_at(lc, band_at(0.4), *centre) == LETHAL_OBSTACLE
    high = lc.costmap(band_at(1.5))
    assert high.cost_at_xy(np.array([centre]))[0] == NO_INFORMATION
    assert not high.lethal.any()


def test_unconfirmed_object_costs_by_existence() -> None:
    lc = stack(existence_confirm=0.6)
    lc.update_objects([coffee_table(existence=0.4)], stamp_s=1.0)
    c = cost_at(lc, band_at(0.4), 1.5, 1.3)
    assert c == existence_cost(0.4, 0.6)
    assert 0 < c < INSCRIBED_INFLATED_OBSTACLE


def test_margin_cost_decays_with_distance() -> None:
    lc = stack(clearance_decay_m=0.3)
    lc.update_objects([coffee_table(margin_m=0.2)], stamp_s=1.0)
    band = band_at(0.4)
    xs = [2.1, 2.3, 2.45, 2.6, 2.8, 3.0]  # right of the table edge at x = 2.0
    costs = [cost_at(lc, band, x, 1.3) for x in xs]
    assert costs[0] == INSCRIBED_INFLATED_OBSTACLE  # inside the class margin
    assert all(a >= b for a, b in zip(costs[:-1], costs[1:], strict=True))
    assert costs[1] > costs[-1] > 0
    far = cost_at(lc, band, 3.5, 3.5)  # beyond margin + 3 decay lengths
    assert far == NO_INFORMATION


def test_margin_scales_with_existence() -> None:
    sure, unsure = stack(), stack()
    sure.update_objects([coffee_table(existence=0.9)], 1.0)
    unsure.update_objects([coffee_table(existence=0.3)], 1.0)
    band = band_at(0.4)
    assert cost_at(unsure, band, 2.3, 1.3) < cost_at(sure, band, 2.3, 1.3)


def test_occupancy_and_objects_combine_unknown_only_where_nobody_knows() -> None:
    lc = stack()
    spec = lc.spec
    free_cells = np.argwhere(np.ones((10, 10), bool)) + [60, 60]
    lc.grid.apply(np.array([[65, 5]]), free_cells)
    lc.update_objects([coffee_table()], stamp_s=1.0)
    cm = lc.costmap(band_at(0.4))
    assert cm.cost[65, 65] == FREE_SPACE  # seen free, no object
    assert cm.cost[0, 79] == NO_INFORMATION  # nobody knows
    r, c = spec.cell_of(np.array([[1.5, 1.3]]))[0]
    assert cm.cost[r, c] == LETHAL_OBSTACLE
    assert cm.class_index is not None and cm.class_index[r, c] == CLASSES.index("coffee_table")
    assert cm.class_index[65, 65] == -1


def test_named_rules() -> None:
    a = np.array([[NO_INFORMATION, 10, 200, NO_INFORMATION]], np.uint8)
    b = np.array([[NO_INFORMATION, 50, 0, 7]], np.uint8)
    assert combine_maximum([a, b]).tolist() == [[NO_INFORMATION, 50, 200, 7]]
    assert combine_overwrite([a, b]).tolist() == [[NO_INFORMATION, 50, 0, 7]]
    assert set(COMBINE_RULES) >= {"maximum", "overwrite"}
    with pytest.raises(MapError, match="unknown combination rule"):
        stack(rule="average")


def test_layers_track_freshness() -> None:
    lc = stack()
    assert set(lc.stale_layers(now_s=0.0, max_age_s=2.0)) == {"occupancy", "objects", "margin", "classes", "height"}
    lc.update_objects([coffee_table()], stamp_s=10.0)
    assert lc.stale_layers(now_s=11.0, max_age_s=2.0) == ["occupancy"]
    assert set(lc.stale_layers(now_s=13.0, max_age_s=2.0)) == {"occupancy", "objects", "margin", "classes", "height"}
    assert lc.footprints.is_fresh(11.5, 2.0) and not lc.footprints.is_fresh(12.5, 2.0)


def test_update_reports_touched_window_and_incremental_costmap_matches_full() -> None:
    lc = stack()
    band = band_at(0.4)
    lc.costmap(band)
    b1 = lc.update_objects([coffee_table()], stamp_s=1.0)
    assert not b1.is_empty
    r, c = lc.spec.cell_of(np.array([[1.5, 1.3]]))[0]
    assert b1.r0 <= r < b1.r1 and b1.c0 <= c < b1.c1
    assert lc.update_objects([coffee_table()], stamp_s=2.0).is_empty  # nothing changed
    moved = ObjectFootprint(1, "coffee_table", TABLE + [1.0, 1.5], 0.0, 0.45, existence=0.9, margin_m=0.2)
    chair = ObjectFootprint(2, "chair", TABLE * 0.4, 0.0, 0.9, existence=0.7, margin_m=0.2)
    lc.update_objects([moved, chair], stamp_s=3.0)
    incremental = lc.costmap(band)
    fresh = stack()
    fresh.update_objects([moved, chair], stamp_s=3.0)
    full = fresh.costmap(band)
    assert np.array_equal(incremental.cost, full.cost)
    assert incremental.class_index is not None and full.class_index is not None
    assert np.array_equal(incremental.class_index, full.class_index)
    assert cost_at(lc, band, 1.5, 1.3) != LETHAL_OBSTACLE  # the old place is clear again


def test_class_probability_planes() -> None:
    lc = stack()
    probs = {1: np.array([0.1, 0.8, 0.1])}
    lc.update_objects([coffee_table(existence=0.5)], stamp_s=1.0, class_probs=probs)
    lc.grid.apply(np.zeros((0, 2), int), np.array([[5, 5]]))
    planes = lc.classes.probabilities(lc.spec)
    assert planes.shape == (len(CLASSES) + 1, 80, 80) and planes.dtype == np.uint8
    r, c = lc.spec.cell_of(np.array([[1.5, 1.3]]))[0]
    assert planes[1 + CLASSES.index("coffee_table"), r, c] == round(0.5 * 0.8 * 255)
    assert int(planes[:, r, c].astype(int).sum()) == pytest.approx(255, abs=2)
    assert planes[0, 5, 5] == 255  # observed, no object: certainly nothing
    assert planes[:, 0, 79].sum() == 0  # unobserved: unknown
    with pytest.raises(MapError, match="class probabilities"):
        lc.update_objects([coffee_table()], 2.0, class_probs={1: np.ones(5)})


def test_height_layer() -> None:
    lc = stack()
    chair = ObjectFootprint(2, "chair", TABLE + [1.2, 0.0], 0.0, 0.9, existence=0.7, margin_m=0.0)
    lc.update_objects([coffee_table(), chair], stamp_s=1.0)
    h = lc.heights.heights_m(lc.spec)
    r, c = lc.spec.cell_of(np.array([[1.5, 1.3], [2.7, 1.3], [0.2, 0.2]]))[:, 0], lc.spec.cell_of(
        np.array([[1.5, 1.3], [2.7, 1.3], [0.2, 0.2]]))[:, 1]
    assert h[r[0], c[0]] == pytest.approx(0.45)
    assert h[r[1], c[1]] == pytest.approx(0.9)
    assert np.isnan(h[r[2], c[2]])


def test_grid_growth_redraws_objects() -> None:
    grid = ProbabilityGrid(GridSpec(0.05, (0.0, 0.0), (80, 80)), grow_chunk_m=1.0)
    lc = LayeredCostmap(grid, CLASSES)
    lc.update_objects([coffee_table()], 1.0)
    band = band_at(0.4)
    assert cost_at(lc, band, 1.5, 1.3) == LETHAL_OBSTACLE
    grid.ensure_contains(-2.0, -2.0, 4.0, 4.0)
    assert grid.spec.origin_xy_m == pytest.approx((-2.0, -2.0))
    assert cost_at(lc, band, 1.5, 1.3) == LETHAL_OBSTACLE
    assert Bounds(0, 0, 2, 2).union(Bounds.empty()) == Bounds(0, 0, 2, 2)


def test_sub_cell_footprint_refinements_do_not_redraw() -> None:
    lc = stack()
    lc.update_objects([coffee_table()], stamp_s=1.0)
    nudged = ObjectFootprint(1, "coffee_table", TABLE + 0.005, 0.0, 0.45, existence=0.9, margin_m=0.2)
    assert lc.update_objects([nudged], stamp_s=2.0).is_empty  # 5 mm < a quarter of 5 cm
    assert np.allclose(lc.costmap(band_at(0.4)).objects[0].polygon_xy_m, TABLE + 0.005)
    moved = ObjectFootprint(1, "coffee_table", TABLE + 0.03, 0.0, 0.45, existence=0.9, margin_m=0.2)
    assert not lc.update_objects([moved], stamp_s=3.0).is_empty


@pytest.mark.parametrize("altitude_m", [0.4, 1.5])
def test_paint_objects_costs_objects_as_the_layer_stack_does(altitude_m: float) -> None:
    # One owner: a costmap from elsewhere gets exactly the map's footprint, margin and decay.
    lc = stack(clearance_decay_m=0.2)
    objects = [coffee_table(existence=0.9), ObjectFootprint(2, "desk", TABLE + 1.2, 0.0, 0.75, existence=0.4, margin_m=0.1)]
    lc.update_objects(objects, stamp_s=1.0)
    band = band_at(altitude_m)
    layered = lc.costmap(band)
    unknown = Costmap(lc.spec, np.full(lc.spec.shape_rc, NO_INFORMATION, np.uint8), band, clearance_decay_m=0.2)
    painted = paint_objects(unknown, objects, band, existence_confirm=0.6)
    np.testing.assert_array_equal(painted.cost, layered.cost)
    assert painted.clearance_decay_m == layered.clearance_decay_m == 0.2


def test_paint_objects_gives_footprints_without_a_margin_their_class_margin() -> None:
    band = band_at(0.4)
    base = Costmap(GridSpec(0.05, (0.0, 0.0), (80, 80)), np.full((80, 80), FREE_SPACE, np.uint8), band)
    unset, none = coffee_table(margin_m=None), coffee_table(margin_m=0.0, oid=2)
    cm = paint_objects(base, [unset, none], band, class_margins_m={"coffee_table": 0.3})
    assert [o.margin_m for o in cm.objects] == [0.3, 0.0]
    assert paint_objects(base, [unset], band).objects[0].margin_m == 0.0  # a class it was not told


def test_the_layers_refuse_a_footprint_whose_margin_was_not_resolved() -> None:
    with pytest.raises(MapError, match=r"object 1 \(coffee_table\): margin_m is None"):
        stack().update_objects([coffee_table(margin_m=None)], stamp_s=1.0)
