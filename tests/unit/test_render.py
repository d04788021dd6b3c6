"""The simulated RGB-D camera: depth geometry, noise model, masks, reproducibility."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from companion.config import CompanionConfig
from companion.errors import SimulationError
from companion.sim.d455 import exact_depth
from companion.sim.render import DepthNoise, RoomRenderer, renderer_from_config
from companion.sim.world import Box, FurnitureObject, Room, generate_room
from semmap.frames import R_BODY_CAMERA_FORWARD, make_transform, pose_from_xyz_rpy, transform_points
from semmap.pointcloud import backproject
from semmap.types import CameraIntrinsics

pytest.importorskip("open3d")

CLASSES = [c.name for c in CompanionConfig().classes]
INTR = CameraIntrinsics(383.0, 383.0, 320.0, 240.0, 640, 480)
HALF = CameraIntrinsics(191.5, 191.5, 160.0, 120.0, 320, 240)
SMALL = CameraIntrinsics(120.0, 120.0, 80.0, 60.0, 160, 120)
EXACT = exact_depth()


def empty_room(width_m: float = 8.0, depth_m: float = 6.0, height_m: float = 2.6) -> Room:
    """Four closed walls, no doorways, no furniture."""
    t = 0.12
    walls = (
        Box((width_m / 2, -t / 2, height_m / 2), (width_m + 2 * t, t, height_m)),
        Box((width_m / 2, depth_m + t / 2, height_m / 2), (width_m + 2 * t, t, height_m)),
        Box((-t / 2, depth_m / 2, height_m / 2), (t, depth_m, height_m)),
        Box((width_m + t / 2, depth_m / 2, height_m / 2), (t, depth_m, height_m)),
    )
    return Room(0, width_m, depth_m, height_m, walls, (), ())


def camera_facing_east(x_m: float, y_m: float, z_m: float, yaw_rad: float = 0.0) -> np.ndarray:
    """Optical camera at a point looking horizontally along map +x (rotated by yaw)."""
    return pose_from_xyz_rpy(x_m, y_m, z_m, 0.0, 0.0, yaw_rad) @ make_transform(
        R_BODY_CAMERA_FORWARD, np.zeros(3)
    )


def box_distance_m(box: Box, pts: np.ndarray) -> np.ndarray:
    """(N,) distance from (N, 3) points to an oriented box (0 inside)."""
    c, s = math.cos(box.yaw_rad), math.sin(box.yaw_rad)
    d = pts - np.asarray(box.center_m)
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)
    excess = np.maximum(np.abs(local) - np.asarray(box.size_m) / 2, 0.0)
    return np.linalg.norm(excess, axis=1)


@pytest.fixture(scope="module")
def wall_renderer() -> RoomRenderer:
    return RoomRenderer(empty_room(), CLASSES, HALF, noise=DepthNoise(noise_coeff=0.003), seed=3)


@pytest.fixture(scope="module")
def furnished() -> tuple[Room, RoomRenderer]:
    room = generate_room(0, n_objects=8)
    return room, RoomRenderer(room, CLASSES, HALF, noise=EXACT, seed=0)


def central_window(img: np.ndarray, frac: float = 0.25) -> np.ndarray:
    H, W = img.shape[:2]
    return img[int(H * frac):int(H * (1 - frac)), int(W * frac):int(W * (1 - frac))]


def test_flat_wall_gives_its_distance_as_z_depth() -> None:
    r = RoomRenderer(empty_room(), CLASSES, INTR, noise=EXACT)
    frame = r.render(camera_facing_east(6.5, 3.0, 1.3))  # east wall's inner face at x = 8
    win = central_window(frame.depth_m)
    # z-depth (not range along the ray): the same everywhere on a fronto-parallel plane.
    assert np.allclose(win, 1.5, atol=1e-4)
    assert frame.depth_m.dtype == np.float32 and frame.depth_m.shape == (480, 640)
    assert frame.rgb.dtype == np.uint8 and frame.rgb.shape == (480, 640, 3)
    assert np.all(frame.masks["instance"] == 0) and np.all(frame.masks["class"] == -1)


@pytest.mark.parametrize("distance_m", [1.0, 2.0, 3.5])
def test_depth_noise_grows_with_z_squared(wall_renderer: RoomRenderer, distance_m: float) -> None:
    frame = wall_renderer.render(camera_facing_east(8.0 - distance_m, 3.0, 1.3), index=int(distance_m * 10))
    win = central_window(frame.depth_m, 0.3).astype(np.float64)
    assert np.all(win > 0)
    err = win - distance_m
    expected_sigma = 0.003 * distance_m**2
    assert abs(err.mean()) < 0.1 * expected_sigma + 0.001
    assert err.std() == pytest.approx(expected_sigma, rel=0.1)


def test_depth_outside_the_range_is_invalid() -> None:
    room = empty_room()
    near = RoomRenderer(room, CLASSES, INTR, noise=DepthNoise(noise_coeff=0.0, min_m=2.0, max_m=6.0))
    assert np.all(central_window(near.render(camera_facing_east(6.5, 3.0, 1.3)).depth_m) == 0.0)
    far = near.render(camera_facing_east(1.0, 3.0, 1.3))  # wall 7 m away, max 6 m
    assert np.all(far.depth_m[220:260, 160:480] == 0.0)  # the wall, around the horizon
    # The floor close to the camera is still measured.
    assert np.any(far.depth_m > 0)
    assert far.depth_m.max() <= 6.0


def test_same_index_reproduces_the_frame_and_another_index_changes_the_noise(
    wall_renderer: RoomRenderer,
) -> None:
    T = camera_facing_east(5.0, 3.0, 1.3)
    a, b = wall_renderer.render(T, index=4), wall_renderer.render(T, index=4)
    c = wall_renderer.render(T, index=5)
    assert np.array_equal(a.depth_m, b.depth_m) and np.array_equal(a.rgb, b.rgb)
    assert not np.array_equal(a.depth_m, c.depth_m)
    rng = np.random.default_rng(11)
    d = wall_renderer.render(T, rng=rng)
    e = wall_renderer.render(T, rng=np.random.default_rng(11))
    assert np.array_equal(d.depth_m, e.depth_m)


def object_poses(room: Room) -> list[np.ndarray]:
    """Camera poses at 1 m looking at each object from 2 m away (inside the room)."""
    poses = []
    for obj in room.objects:
        cx, cy = obj.center_xy_m
        for ang in np.linspace(0, 2 * np.pi, 8, endpoint=False):
            x, y = cx + 2.0 * math.cos(ang), cy + 2.0 * math.sin(ang)
            if 0.3 < x < room.width_m - 0.3 and 0.3 < y < room.depth_m - 0.3:
                poses.append(camera_facing_east(x, y, 1.0, ang + math.pi))
                break
    return poses


def check_masks_match_geometry(room: Room, r: RoomRenderer, T: np.ndarray) -> int:
    frame = r.render(T)
    inst, cls = frame.masks["instance"], frame.masks["class"]
    pts_cam, uv = backproject(frame.depth_m, frame.intrinsics, min_m=0.05, max_m=50.0)
    pts_map = transform_points(T, pts_cam)
    ids = inst[uv[:, 1], uv[:, 0]]
    checked = 0
    for obj in room.objects:
        sel = ids == obj.object_id
        if not np.any(sel):
            continue
        dist = np.min([box_distance_m(b, pts_map[sel]) for b in obj.parts], axis=0)
        assert np.max(dist) < 2e-3, f"object {obj.object_id} pixels land {dist.max():.3f} m off its boxes"
        assert np.all(cls[inst == obj.object_id] == CLASSES.index(obj.class_name))
        checked += 1
    # Pixels labelled "no object" never land inside an object.
    none = pts_map[ids == 0]
    for obj in room.objects:
        for b in obj.parts:
            inside = box_distance_m(Box(b.center_m, tuple(s - 0.01 for s in b.size_m), b.yaw_rad), none)
            assert np.all(inside > 0.0)
    return checked


def test_instance_pixels_backproject_onto_their_objects(furnished: tuple[Room, RoomRenderer]) -> None:
    room, r = furnished
    seen = sum(check_masks_match_geometry(room, r, T) for T in object_poses(room)[:4])
    assert seen >= 4


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    x=st.floats(0.5, 7.5), y=st.floats(0.5, 5.5), z=st.floats(0.4, 2.2),
    yaw=st.floats(-math.pi, math.pi), pitch=st.floats(-0.6, 0.6),
)
def test_masks_match_geometry_from_any_pose(
    furnished: tuple[Room, RoomRenderer], x: float, y: float, z: float, yaw: float, pitch: float
) -> None:
    room, r = furnished
    T = pose_from_xyz_rpy(x, y, z, 0.0, pitch, yaw) @ make_transform(R_BODY_CAMERA_FORWARD, np.zeros(3))
    check_masks_match_geometry(room, r, T)


@pytest.mark.parametrize("pose", [(1.0, 1.0, 1.0, 0.3, 0.4), (5.0, 2.5, 0.5, 2.0, -0.3),
                                  (2.0, 4.5, 2.2, -2.5, 0.7), (7.5, 0.5, 1.5, 2.4, 0.0)])
def test_analytic_floor_and_ceiling_match_the_full_ray_cast(
    furnished: tuple[Room, RoomRenderer], pose: tuple[float, float, float, float, float],
) -> None:
    _, r = furnished
    x, y, z, yaw, pitch = pose
    T = pose_from_xyz_rpy(x, y, z, 0.0, pitch, yaw) @ make_transform(R_BODY_CAMERA_FORWARD, np.zeros(3))
    fast = {k: np.array(v, copy=True) for k, v in r.cast(T).items() if k != "T"}
    r.analytic_slabs = False
    try:
        full = r.cast(T)
    finally:
        r.analytic_slabs = True
    same_prim = fast["prim"] == full["prim"]
    assert same_prim.mean() > 0.999  # differences only where two surfaces meet at a pixel
    assert np.array_equal(fast["face"][same_prim], full["face"][same_prim])
    both = same_prim & np.isfinite(full["depth_m"])
    assert np.allclose(fast["depth_m"][both], full["depth_m"][both], rtol=1e-4, atol=1e-4)
    assert np.any(fast["prim"] == 0) or np.any(fast["prim"] == 1)  # the pose sees floor or ceiling


def test_visible_objects_report_mask_pixels_and_ground_truth(furnished: tuple[Room, RoomRenderer]) -> None:
    room, r = furnished
    T = object_poses(room)[0]
    frame = r.render(T)
    vis = r.visible_objects(frame)
    inst = frame.masks["instance"]
    assert vis, "the camera looks straight at an object"
    assert sum(v.pixel_count for v in vis) == int(np.count_nonzero(inst))
    assert [v.pixel_count for v in vis] == sorted((v.pixel_count for v in vis), reverse=True)
    for v in vis:
        obj = room.object_by_id(v.object_id)
        vv, uu = np.nonzero(inst == v.object_id)
        u0, v0, u1, v1 = v.bbox_xyxy_px
        assert (u0, v0, u1, v1) == (uu.min(), vv.min(), uu.max() + 1, vv.max() + 1)
        assert v.class_name == obj.class_name and v.class_index == CLASSES.index(obj.class_name)
        assert np.allclose(v.footprint_xy_m, obj.footprint_xy_m())
        assert v.height_m == pytest.approx(obj.height_m)
    assert r.visible_objects(frame, min_pixels=10**9) == []


def test_silhouette_is_what_each_object_covers_alone(furnished: tuple[Room, RoomRenderer]) -> None:
    """With no margin and one ray per pixel, an object's silhouette is exactly its mask in a
    render of the room with that object alone; with others in front it covers more than
    its visible pixels."""
    room, r = furnished
    occluded = 0
    for T in object_poses(room)[:3]:
        inst = r.render(T).masks["instance"]
        sil = r.silhouette_px(T, margin_images=0.0, stride_px=1)
        for obj in room.objects:
            alone = RoomRenderer(dataclasses.replace(room, objects=(obj,)), CLASSES, HALF, noise=EXACT)
            n_alone = int(np.count_nonzero(alone.render(T).masks["instance"] == obj.object_id))
            assert sil.get(obj.object_id, 0.0) == n_alone
            n_visible = int(np.count_nonzero(inst == obj.object_id))
            assert n_visible <= n_alone
            occluded += n_visible < n_alone
    assert occluded > 0, "some object is partly hidden behind another from these poses"


def test_silhouette_counts_what_lies_beyond_the_image_border() -> None:
    """A thin board facing the camera, half past the right border: the image holds half of
    it, the extended plane all of it, f**2 * area / distance**2 pixels."""
    d_m, w_m, h_m = 3.0, 1.0, 0.8
    f = HALF.fx_px
    half_w_m = (HALF.width_px - HALF.cx_px) / f * d_m  # image-plane half width at the board
    board = Box((4.0 + d_m, 3.0 - half_w_m, 1.0), (0.01, w_m, h_m))  # centred on the right border
    obj = FurnitureObject(1, "whiteboard", (board.center_m[0], board.center_m[1]), 0.0, board.size_m, (board,), (255, 255, 255))
    room = dataclasses.replace(empty_room(), objects=(obj,))
    r = RoomRenderer(room, CLASSES, HALF, noise=EXACT)
    T = camera_facing_east(4.0, 3.0, 1.0)
    expected_px = f * f * w_m * h_m / d_m**2
    in_image = r.silhouette_px(T, margin_images=0.0, stride_px=1)[1]
    assert in_image == int(np.count_nonzero(r.render(T).masks["instance"] == 1))
    assert in_image == pytest.approx(expected_px / 2, rel=0.03)
    assert r.silhouette_px(T)[1] == pytest.approx(expected_px, rel=0.03)
    assert r.silhouette_px(T, stride_px=3)[1] == pytest.approx(expected_px, rel=0.05)
    with pytest.raises(SimulationError, match="stride_px"):
        r.silhouette_px(T, stride_px=0)


def test_edge_dropout_invalidates_depth_discontinuities(furnished: tuple[Room, RoomRenderer]) -> None:
    room, _ = furnished
    T = object_poses(room)[0]
    # Only edge dropout differs (the other D455 effects off, so they cannot mask it).
    keep = RoomRenderer(room, CLASSES, INTR, noise=exact_depth(max_m=50.0))
    drop = RoomRenderer(room, CLASSES, INTR, noise=dataclasses.replace(exact_depth(max_m=50.0), edge_dropout=1.0))
    a, b = keep.render(T).depth_m, drop.render(T).depth_m
    jump = np.abs(np.diff(a, axis=1)) > 0.3
    vv, uu = np.nonzero(jump)
    assert len(vv) > 20
    assert np.all(b[vv, uu] == 0) and np.all(b[vv, uu + 1] == 0)
    # Away from edges dropout changes nothing.
    assert np.mean(b == a) > 0.9


def test_floor_texture_gives_trackable_corners() -> None:
    r = RoomRenderer(empty_room(), CLASSES, INTR, seed=1)
    # Looking down at the floor at 45 degrees, as the tracker's motion compensation needs.
    T = pose_from_xyz_rpy(4.0, 3.0, 1.2, 0.0, math.radians(45), 0.0) @ make_transform(
        R_BODY_CAMERA_FORWARD, np.zeros(3)
    )
    frame = r.render(T)
    gray = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY)
    corners = cv2.goodFeaturesToTrack(gray, maxCorners=500, qualityLevel=0.01, minDistance=8)
    assert corners is not None and len(corners) > 80
    # Texture moves with the surface: a sideways shift of 5 cm shifts the image, not noise.
    T2 = T.copy()
    T2[1, 3] += 0.05
    moved = cv2.cvtColor(r.render(T2).rgb, cv2.COLOR_RGB2GRAY)
    nxt, status, _ = cv2.calcOpticalFlowPyrLK(gray, moved, corners, None)
    flow = (nxt - corners)[status[:, 0] == 1, 0]
    assert len(flow) > 50
    # Looking east, north is the image's left: the camera moved left, so the floor's
    # features move right (positive u), all together.
    assert np.median(flow[:, 0]) > 1.0
    assert np.abs(np.median(flow[:, 1])) < 1.0


def test_renderer_from_config_uses_camera_and_sim_settings() -> None:
    cfg = CompanionConfig.model_validate(
        {"camera": {"width_px": 160, "height_px": 120, "fx_px": 120, "fy_px": 120, "cx_px": 80,
                    "cy_px": 60, "depth_max_m": 4.0}, "sim": {"depth_noise_coeff": 0.01, "seed": 5}}
    )
    r = renderer_from_config(empty_room(), cfg)
    assert r.intrinsics == SMALL
    assert r.noise.max_m == 4.0 and r.noise.noise_coeff == 0.01 and r.seed == 5
    frame = r.render(camera_facing_east(4.0, 3.0, 1.3))
    assert frame.rgb.shape == (120, 160, 3)
    assert frame.depth_m.max() <= 4.0


def test_bad_pose_is_rejected(wall_renderer: RoomRenderer) -> None:
    from companion.errors import SimulationError

    with pytest.raises(SimulationError, match="T_map_camera"):
        wall_renderer.render(np.eye(3))
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(SimulationError, match="finite"):
        wall_renderer.render(bad)


def test_frame_is_the_same_whatever_the_shading_thread_count() -> None:
    """Bands on a thread pool split the work only: every random draw stays in the caller's
    thread in a fixed order, so the frame is bit-identical with 1, 2 or 3 shading threads."""
    cfg = CompanionConfig()
    room = generate_room(seed=5)
    cam = camera_facing_east(1.0, room.depth_m / 2.0, 1.2, yaw_rad=0.3)
    frames = []
    for threads in (1, 2, 3):
        r = renderer_from_config(room, cfg, seed=11)
        r.shade_threads = threads
        frames.append(r.render(cam, index=4))
        r.close()
    for other in frames[1:]:
        assert np.array_equal(frames[0].rgb, other.rgb)
        assert np.array_equal(frames[0].depth_m, other.depth_m)
        assert np.array_equal(frames[0].masks["instance"], other.masks["instance"])
    assert len(np.unique(frames[0].masks["instance"])) > 1  # furniture in view: a real test
