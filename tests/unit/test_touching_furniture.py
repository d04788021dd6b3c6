"""Objects that touch: shape priors and the other boxes of the frame decide whose points are whose."""

from __future__ import annotations

import numpy as np

from semmap.config import ClassConfig, GeometryConfig, default_classes
from semmap.frame_objects import observe_frame
from semmap.geometry import _widest_top, observe_object
from semmap.polygons import convex_intersection, convex_iou, polygon_area_m2
from semmap.shape_prior import horizontal_layers, shape_mask
from semmap.types import Track
from tests.unit.test_geometry import FLOOR, K, box_of, camera_pose, render

DESK = ClassConfig(name="desk", hollow="full", margin_m=0.2, color_rgb=(1, 2, 3), shape="table")
CHAIR = ClassConfig(name="chair", hollow="full", margin_m=0.2, color_rgb=(1, 2, 3), shape="seat")
CLASSES = {"desk": DESK, "chair": CHAIR}

# A 1.0 x 1.8 m dining table, top 0.72-0.75 m, at x 2.0-3.0, y 0.0-1.8, on the floor z = 0.
TABLE = [((2.0, 0.0, 0.72), (3.0, 1.8, 0.75))] + [
    ((x, y, 0.0), (x + 0.05, y + 0.05, 0.72)) for x in (2.02, 2.93) for y in (0.02, 1.73)]
TABLE_FOOTPRINT = np.array([[2.0, 0.0], [3.0, 0.0], [3.0, 1.8], [2.0, 1.8]])
# A chair pushed in from the camera's side: its back touches the table's edge and rises to
# 1.0 m, its seat (0.42-0.45 m) is under the top.
NEAR_CHAIR = [((1.93, 0.7, 0.45), (1.97, 1.15, 1.0)), ((1.93, 0.7, 0.42), (2.38, 1.15, 0.45))] + [
    ((x, y, 0.0), (x + 0.03, y + 0.03, 0.42)) for x in (1.94, 2.34) for y in (0.71, 1.11)]
# A chair on the far side: only its back shows above the top, the top is in front of its box.
FAR_CHAIR = [((3.28, 0.5, 0.45), (3.32, 0.95, 1.0)), ((2.85, 0.5, 0.42), (3.3, 0.95, 0.45))] + [
    ((x, y, 0.0), (x + 0.03, y + 0.03, 0.42)) for x in (2.86, 3.26) for y in (0.51, 0.91)]
T_CAM = camera_pose(0.6, 0.9, 1.4, 0.0, 30.0)


def _observe(boxes: list, cls: ClassConfig, scene: list) -> object:
    depth = render(scene + [FLOOR], T_CAM)
    track = Track(1, box_of(boxes, T_CAM), 0.8, cls.name)
    return observe_object(depth, K, T_CAM, track, cls, GeometryConfig(), depth_range_m=(0.3, 8.0))


def test_a_table_is_its_top_not_the_chair_back_rising_above_it() -> None:
    obs = _observe(TABLE, DESK, TABLE + NEAR_CHAIR)
    assert obs is not None
    # Without the prior the table's cluster carries the chair back: 1.0 m high.
    assert obs.z_max_m < 0.8
    assert obs.top_height_m is not None and abs(obs.top_height_m - 0.75) < 0.03
    assert convex_iou(obs.footprint_xy_m, TABLE_FOOTPRINT) > 0.6
    free = ClassConfig(name="desk", hollow="full", margin_m=0.2, color_rgb=(1, 2, 3))
    plain = _observe(TABLE, free, TABLE + NEAR_CHAIR)
    assert plain is not None and plain.z_max_m > 0.95  # the scene does join them


def test_a_seat_cluster_drops_the_large_table_top_it_touches() -> None:
    rng = np.random.default_rng(0)
    top = np.column_stack([rng.uniform(2.0, 3.0, 1500), rng.uniform(0.0, 1.8, 1500), rng.uniform(0.72, 0.75, 1500)])
    back = np.column_stack([rng.uniform(1.93, 1.97, 300), rng.uniform(0.7, 1.15, 300), rng.uniform(0.45, 1.0, 300)])
    seat = np.column_stack([rng.uniform(1.93, 2.38, 300), rng.uniform(0.7, 1.15, 300), rng.uniform(0.42, 0.45, 300)])
    pts = np.concatenate([top, back, seat])
    keep = shape_mask(pts, pts[:, 2], "seat", 0.03, 15)
    assert keep[: len(top)].mean() < 0.01  # crumbs at the top's corners, dropped by re-clustering
    assert keep[len(top):].mean() > 0.9  # the chair's own back and seat stay
    # A chair's own seat and a thin back rail are not a foreign top.
    own = shape_mask(pts[len(top):], pts[len(top):, 2], "seat", 0.03, 15)
    assert own.all()


def test_the_highest_large_layer_is_the_table_top_and_things_on_it_are_not() -> None:
    rng = np.random.default_rng(1)
    top = np.column_stack([rng.uniform(0, 1.2, 2000), rng.uniform(0, 0.7, 2000), rng.uniform(0.72, 0.75, 2000)])
    cup = np.column_stack([rng.uniform(0.5, 0.58, 60), rng.uniform(0.3, 0.38, 60), rng.uniform(0.75, 0.85, 60)])
    shelf = np.column_stack([rng.uniform(0, 1.2, 900), rng.uniform(0, 0.7, 900), rng.uniform(0.30, 0.32, 900)])
    pts = np.concatenate([top, cup, shelf])
    layers = horizontal_layers(pts, pts[:, 2], 0.03, 15)
    assert abs(layers[-1].height_m - 0.735) < 0.03 and len(layers) == 2
    keep = shape_mask(pts, pts[:, 2], "table", 0.03, 15)
    assert keep[:2000].all() and keep[2000 + 60:].all()
    assert not keep[2000:2060][cup[:, 2] > 0.79].any()  # what stands on the top is not the table


def test_points_of_a_nearer_object_in_the_frame_are_not_the_farther_ones() -> None:
    scene = TABLE + FAR_CHAIR
    depth = render(scene + [FLOOR], T_CAM)
    far = Track(2, box_of(FAR_CHAIR, T_CAM), 0.8, "chair")
    table = Track(1, box_of(TABLE, T_CAM), 0.8, "desk")
    alone = observe_object(depth, K, T_CAM, far, CHAIR, GeometryConfig(), depth_range_m=(0.3, 8.0))
    free = ClassConfig(name="chair", hollow="full", margin_m=0.2, color_rgb=(1, 2, 3))
    plain = observe_object(depth, K, T_CAM, far, free, GeometryConfig(), depth_range_m=(0.3, 8.0))
    obs = observe_frame(depth, K, T_CAM, [table, far], CLASSES, GeometryConfig(), depth_range_m=(0.3, 8.0))
    chair = next(o for o in obs if o.track_id == 2)
    # The chair's box holds the nearer table top: without a prior it is taken for the chair,
    # with the seat prior alone the box shows nothing of its own.
    assert plain is not None and plain.centroid_map_m[0] < 3.0 and plain.z_max_m < 0.8
    assert alone is None
    assert chair.z_min_m > 0.6 and chair.z_max_m > 0.95
    assert abs(chair.centroid_map_m[0] - 3.3) < 0.1 and polygon_area_m2(chair.footprint_xy_m) < 0.3
    desk = next(o for o in obs if o.track_id == 1)
    assert desk.z_max_m < 0.8


# Three chairs side by side in front of the table (backs towards the camera), pulled 0.3 m
# out: a cluster of their own, nearer than the table and as wide as its box.
CHAIR_ROW = [((1.3, y, 0.0), (1.7, y + 0.6, 0.45)) for y in (0.0, 0.6, 1.2)] + [
    ((1.3, y, 0.45), (1.34, y + 0.6, 0.85)) for y in (0.0, 0.6, 1.2)]


def test_a_table_box_shows_the_table_top_not_the_chairs_in_front_of_it() -> None:
    T = camera_pose(-0.6, 0.9, 1.6, 0.0, 30.0)
    depth = render(TABLE + CHAIR_ROW + [FLOOR], T)
    track = Track(1, box_of(TABLE, T), 0.8, "desk")
    obs = observe_object(depth, K, T, track, DESK, GeometryConfig(), depth_range_m=(0.3, 8.0))
    assert obs is not None
    # The nearest large cluster spanning the box is the chair row; its highest surface is a
    # row of backrests, the table's is its top.
    assert obs.footprint_xy_m[:, 0].min() > 1.95  # on the table, none of the chairs
    assert np.ptp(obs.footprint_xy_m[:, 1]) > 1.6  # the top's whole length
    assert obs.top_height_m is not None and abs(obs.top_height_m - 0.75) < 0.03


def test_a_farther_wider_top_at_another_class_height_is_not_the_tables() -> None:
    rng = np.random.default_rng(2)
    # The nearest cluster's highest surface is a strip (a backrest's top rail), no table top.
    small = np.column_stack([rng.uniform(0, 1.0, 800), rng.uniform(0, 0.1, 800), rng.uniform(0.43, 0.46, 800)])
    wide = np.column_stack([rng.uniform(1.5, 3.5, 2500), rng.uniform(0, 1.2, 2500), rng.uniform(0.97, 1.0, 2500)])
    vox = np.concatenate([small, wide])
    labels = np.repeat([0, 1], [len(small), len(wide)])
    coffee = next(c for c in default_classes() if c.name == "coffee_table")
    # A counter 1.0 m high behind a coffee table spans its box too: not the coffee table's top.
    assert _widest_top(vox, labels, vox[:, 2], [0, 1], coffee, GeometryConfig()) == 0
    # The same wider top at a coffee table's height is the table the box shows.
    low = vox.copy()
    low[len(small):, 2] -= 0.55
    assert _widest_top(low, labels, low[:, 2], [0, 1], coffee, GeometryConfig()) == 1
    # A nearer top of the class's height and width is the table, a wider one behind it not.
    top = small.copy()
    top[:, 1] *= 6.0
    assert _widest_top(np.concatenate([top, low[len(small):]]), labels, np.concatenate([top, low[len(small):]])[:, 2],
                       [0, 1], coffee, GeometryConfig()) == 0


def _chair_at(y0_m: float) -> list:
    """A solid seat 0.45 x 0.45 m and a backrest to 0.9 m, at x 1.3-1.75 m, y y0..y0 + 0.45."""
    return [((1.3, y0_m, 0.0), (1.75, y0_m + 0.45, 0.45)), ((1.3, y0_m, 0.45), (1.34, y0_m + 0.45, 0.9))]


def test_two_chairs_side_by_side_seen_along_the_row_are_each_their_own() -> None:
    near, far = _chair_at(0.0), _chair_at(0.52)
    near_fp = np.array([[1.3, 0.0], [1.75, 0.0], [1.75, 0.45], [1.3, 0.45]])
    far_fp = near_fp + [0.0, 0.52]
    T = camera_pose(-0.8, -2.0, 1.3, np.radians(35.0), 30.0)
    depth = render(near + far + [FLOOR], T)
    tracks = [Track(1, box_of(near, T), 0.8, "chair"), Track(2, box_of(far, T), 0.8, "chair")]
    obs = {o.track_id: o for o in observe_frame(depth, K, T, tracks, CLASSES, GeometryConfig(),
                                                depth_range_m=(0.3, 8.0))}
    # The 7 cm gap does not part the two in depth: the near chair's box holds one cluster
    # spanning both. Each box keeps only its own chair (of the far one only the backrest shows).
    for tid, other in ((1, far_fp), (2, near_fp)):
        assert polygon_area_m2(convex_intersection(obs[tid].footprint_xy_m, other)) < 0.02, tid
    assert polygon_area_m2(convex_intersection(obs[1].footprint_xy_m, near_fp)) > 0.6 * polygon_area_m2(near_fp)
    assert obs[2].centroid_map_m[1] > 0.6
