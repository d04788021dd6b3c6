"""Per-detection object geometry on analytically ray-cast depth images."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semmap.config import ClassConfig, ExtrinsicsConfig, GeometryConfig
from semmap.frames import invert, pose_from_xyz_rpy, transform_points
from semmap.geometry import observe_object
from semmap.polygons import convex_footprint, convex_iou, min_area_rectangle, polygon_area_m2
from semmap.ransac import Plane
from semmap.types import CameraIntrinsics, Track

K = CameraIntrinsics(200.0, 200.0, 160.0, 120.0, 320, 240)
TABLE = ClassConfig(name="desk", hollow="full", margin_m=0.2, color_rgb=(1, 2, 3))
SOFA = ClassConfig(name="sofa", hollow="none", margin_m=0.2, color_rgb=(1, 2, 3))

# A 1.2 x 0.7 m table, top 0.72-0.75 m, four 5 cm legs, centred at (3, 1) on the floor z = 0.
TABLE_BOXES = [((2.4, 0.65, 0.72), (3.6, 1.35, 0.75))] + [
    ((x, y, 0.0), (x + 0.05, y + 0.05, 0.72))
    for x in (2.42, 3.53) for y in (0.67, 1.28)
]
FLOOR = ((-10.0, -10.0, -1.0), (10.0, 10.0, 0.0))


def render(boxes: list, T_map_camera: np.ndarray) -> np.ndarray:
    """Depth (H, W) of axis-aligned boxes (lo, hi) by the slab method, 0 where nothing is hit."""
    vv, uu = np.mgrid[0 : K.height_px, 0 : K.width_px]
    d_cam = np.stack([(uu - K.cx_px) / K.fx_px, (vv - K.cy_px) / K.fy_px, np.ones_like(uu, float)], -1)
    d = d_cam.reshape(-1, 3) @ T_map_camera[:3, :3].T  # (N, 3) map-frame rays, z-depth = t
    o = T_map_camera[:3, 3]
    best = np.full(len(d), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for lo, hi in boxes:
            t1 = (np.asarray(lo) - o) / d
            t2 = (np.asarray(hi) - o) / d
            tmin = np.nanmax(np.minimum(t1, t2), axis=1)
            tmax = np.nanmin(np.maximum(t1, t2), axis=1)
            hit = (tmax >= tmin) & (tmin > 0)
            best = np.where(hit & (tmin < best), tmin, best)
    best[~np.isfinite(best)] = 0.0
    return best.reshape(K.height_px, K.width_px).astype(np.float32)


def camera_pose(x: float, y: float, z: float, yaw: float, pitch_deg: float) -> np.ndarray:
    T_map_body = pose_from_xyz_rpy(x, y, z, 0.0, 0.0, yaw)
    return T_map_body @ ExtrinsicsConfig(xyz_m=(0.1, 0.0, 0.0), rpy_deg=(0, pitch_deg, 0)).T_body_camera()


def box_of(boxes: list, T_map_camera: np.ndarray) -> tuple[float, float, float, float]:
    """Tight image box of the corners of ``boxes``."""
    corners = np.array([[x, y, z] for lo, hi in boxes for x in (lo[0], hi[0])
                        for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    pc = transform_points(invert(T_map_camera), corners)
    u = K.fx_px * pc[:, 0] / pc[:, 2] + K.cx_px
    v = K.fy_px * pc[:, 1] / pc[:, 2] + K.cy_px
    return (max(0.0, u.min()), max(0.0, v.min()), min(K.width_px, u.max()), min(K.height_px, v.max()))


def observe(depth: np.ndarray, T: np.ndarray, cls: ClassConfig = TABLE, remove_walls: bool = True, **kw):
    track = Track(7, box_of(TABLE_BOXES, T), 0.9, cls.name)
    return observe_object(depth, K, T, track, cls, GeometryConfig(**kw), depth_range_m=(0.3, 8.0),
                          remove_walls=remove_walls)


TRUE_FOOTPRINT = np.array([[2.4, 0.65], [3.6, 0.65], [3.6, 1.35], [2.4, 1.35]])


def test_table_footprint_height_and_top_from_one_view() -> None:
    T = camera_pose(1.0, 1.0, 1.5, 0.0, 30.0)
    obs = observe(render(TABLE_BOXES + [FLOOR], T), T)
    assert obs is not None
    assert obs.track_id == 7 and obs.class_name == "desk"
    # The footprint covers the top, so the space between the legs is inside it.
    assert convex_iou(obs.footprint_xy_m, TRUE_FOOTPRINT) > 0.85
    assert obs.z_max_m == pytest.approx(0.75, abs=0.03)
    assert obs.z_min_m == 0.0  # standing on the floor
    assert obs.top_plane is not None and obs.top_height_m == pytest.approx(0.75, abs=0.02)
    assert obs.top_plane.normal[2] > 0.99
    # The centroid of the visible points leans towards the camera (the top's front face).
    assert np.linalg.norm(obs.centroid_xy_m - [3.0, 1.0]) < 0.35
    assert obs.range_m == pytest.approx(np.linalg.norm(np.array(obs.centroid_map_m) - T[:3, 3]))


def test_invalid_depth_is_dropped_not_turned_into_points() -> None:
    T = camera_pose(1.0, 1.0, 1.5, 0.0, 30.0)
    depth = render(TABLE_BOXES + [FLOOR], T)
    ref = observe(depth, T)
    rng = np.random.default_rng(0)
    bad = depth.copy()
    holes = rng.random(bad.shape) < 0.2
    bad[holes] = np.where(rng.random(holes.sum()) < 0.5, 0.0, np.nan)
    bad[rng.random(bad.shape) < 0.01] = 50.0  # beyond range
    obs = observe(bad, T)
    assert obs is not None and ref is not None
    assert obs.n_points < ref.n_points
    assert np.linalg.norm(np.subtract(obs.centroid_map_m, ref.centroid_map_m)) < 0.02
    assert obs.z_max_m < 0.8


def test_full_rigid_transform_rotated_camera_gives_the_same_map_geometry() -> None:
    # Two very different poses (one yawed and rolled): the map-frame result must agree.
    T1 = camera_pose(1.0, 1.0, 1.5, 0.0, 30.0)
    T2 = pose_from_xyz_rpy(3.0, -0.8, 1.4, math.radians(5), 0.0, math.radians(90)) @ ExtrinsicsConfig(
        rpy_deg=(0, 35, 0)).T_body_camera()
    o1 = observe(render(TABLE_BOXES + [FLOOR], T1), T1)
    o2 = observe(render(TABLE_BOXES + [FLOOR], T2), T2)
    assert o1 is not None and o2 is not None
    assert o2.z_max_m == pytest.approx(0.75, abs=0.03)
    assert convex_iou(o2.footprint_xy_m, TRUE_FOOTPRINT) > 0.8
    c1 = min_area_rectangle(o1.footprint_xy_m).mean(axis=0)
    c2 = min_area_rectangle(o2.footprint_xy_m).mean(axis=0)
    assert np.linalg.norm(c1 - c2) < 0.1


def test_background_wall_and_far_clutter_are_not_the_object() -> None:
    T = camera_pose(1.0, 1.0, 1.5, 0.0, 30.0)
    wall = ((4.5, -3.0, 0.0), (4.6, 5.0, 2.5))
    obs = observe(render(TABLE_BOXES + [FLOOR, wall], T), T)
    assert obs is not None
    assert obs.footprint_xy_m[:, 0].max() < 3.8


def test_non_hollow_objects_have_no_top_plane_search_and_floor_only_boxes_give_none() -> None:
    T = camera_pose(1.0, 1.0, 1.5, 0.0, 30.0)
    obs = observe(render(TABLE_BOXES + [FLOOR], T), T, cls=SOFA)
    assert obs is not None and obs.top_plane is None
    assert observe(render([FLOOR], T), T) is None


def test_floor_plane_in_map_frame_gives_true_heights() -> None:
    # The whole scene lifted by 0.3 m, with the floor plane told to the function.
    lift = [((lo[0], lo[1], lo[2] + 0.3), (hi[0], hi[1], hi[2] + 0.3)) for lo, hi in TABLE_BOXES + [FLOOR]]
    T = camera_pose(1.0, 1.0, 1.8, 0.0, 30.0)
    track = Track(1, box_of(lift[:-1], T), 0.9, "desk")
    obs = observe_object(render(lift, T), K, T, track, TABLE, GeometryConfig(),
                         floor=Plane.horizontal(0.3), depth_range_m=(0.3, 8.0))
    assert obs is not None and obs.z_max_m == pytest.approx(0.75, abs=0.03)


@settings(max_examples=50, deadline=None)
@given(
    cx=st.floats(-5, 5), cy=st.floats(-5, 5), w=st.floats(0.1, 3), h=st.floats(0.1, 3),
    yaw=st.floats(-math.pi, math.pi),
)
def test_min_area_rectangle_of_a_rotated_rectangle_is_itself(cx, cy, w, h, yaw) -> None:
    c, s = math.cos(yaw), math.sin(yaw)
    local = np.array([[-w, -h], [w, -h], [w, h], [-w, h]]) / 2
    rect = local @ np.array([[c, -s], [s, c]]).T + [cx, cy]
    rng = np.random.default_rng(0)
    inside = (rng.uniform(-0.5, 0.5, (30, 2)) * [w, h]) @ np.array([[c, -s], [s, c]]).T + [cx, cy]
    out = min_area_rectangle(np.concatenate([rect, inside]))
    assert polygon_area_m2(out) == pytest.approx(w * h, rel=1e-6)
    assert convex_iou(out, rect) == pytest.approx(1.0, abs=1e-6)


def test_convex_iou_and_degenerate_footprints() -> None:
    a = np.array([[0, 0], [2, 0], [2, 1], [0, 1.0]])
    b = a + [1.0, 0.0]
    assert convex_iou(a, b) == pytest.approx(1.0 / 3.0)
    assert convex_iou(a, a[::-1]) == pytest.approx(1.0)
    assert convex_iou(a, a + [5.0, 0.0]) == 0.0
    line = np.column_stack([np.linspace(0, 1, 10), np.zeros(10)])
    fp = convex_footprint(line, min_width_m=0.03)
    assert polygon_area_m2(fp) == pytest.approx(1.0 * 0.03, rel=1e-6)


def test_a_wall_a_few_cm_behind_the_object_is_removed_before_clustering() -> None:
    T = camera_pose(1.0, 1.0, 1.5, 0.0, 30.0)
    # The wall's face is 5 cm behind the table's far edge: one voxel-connected cloud otherwise.
    wall = ((3.65, -3.0, 0.0), (3.75, 5.0, 2.5))
    depth = render(TABLE_BOXES + [FLOOR, wall], T)
    joined = observe(depth, T, remove_walls=False)
    assert joined is not None and np.ptp(joined.footprint_xy_m[:, 1]) > 1.0  # the wall came along
    obs = observe(depth, T)
    assert obs is not None
    assert obs.footprint_xy_m[:, 0].max() < 3.63
    assert np.ptp(obs.footprint_xy_m[:, 1]) < 0.8
    assert convex_iou(obs.footprint_xy_m, TRUE_FOOTPRINT) > 0.7


def test_an_occluder_in_front_is_not_taken_for_a_wall() -> None:
    T = camera_pose(1.0, 1.0, 1.5, 0.0, 30.0)
    # A low screen between the camera and the table fills the pixels below the box.
    screen = ((2.0, -3.0, 0.0), (2.05, 5.0, 0.5))
    obs = observe(render(TABLE_BOXES + [FLOOR, screen], T), T)
    assert obs is not None
    assert obs.footprint_xy_m[:, 0].min() > 2.3


def test_convex_gap_is_zero_on_overlap_and_the_edge_distance_apart() -> None:
    from semmap.polygons import convex_gap_m

    a = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    assert convex_gap_m(a, a + [0.5, 0.5]) == 0.0
    assert convex_gap_m(a, a * 0.2 + 0.4) == 0.0  # one inside the other
    assert convex_gap_m(a, a + [1.3, 0.2]) == pytest.approx(0.3)
    diamond = np.array([[2.0, 0.5], [2.5, 0.0], [3.0, 0.5], [2.5, 1.0]])
    assert convex_gap_m(a, diamond) == pytest.approx(1.0)  # vertex of one to the edge of the other
