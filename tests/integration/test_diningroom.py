"""Object geometry and the object map on real RGB-D frames of a dining room.

Five real frames (640x480, depth in millimetres, camera-to-world poses) with the boxes a
COCO YOLOX-nano found in them. The world frame is roughly the first camera's optical frame,
so the floor is estimated (the lowest large near-horizontal plane) and a gravity-aligned map
frame is built on it before any height is computed.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from semmap.config import GeometryConfig, default_classes
from semmap.frames import make_transform, quaternion_to_rotation, transform_points
from semmap.geometry import ObjectObservation, observe_object
from semmap.grid import GridSpec, rasterize_polygon
from semmap.objects import CameraView, ObjectMap
from semmap.pointcloud import backproject
from semmap.polygons import polygon_area_m2
from semmap.ransac import estimate_floor, gravity_aligned_frame
from semmap.types import CameraIntrinsics, Track

COCO_TO_OURS = {"chair": "chair", "dining table": "desk", "couch": "sofa"}
DEPTH_RANGE_M = (0.3, 6.0)


@pytest.fixture(scope="module")
def scene(real_data: Path):
    root = real_data / "rgbd" / "diningroom"
    meta = json.loads((root / "intrinsics.json").read_text())
    K = CameraIntrinsics(meta["fx"], meta["fy"], meta["cx"], meta["cy"], meta["width"], meta["height"])
    poses = []
    for line in (root / "pose.txt").read_text().splitlines():
        tx, ty, tz, qx, qy, qz, qw = map(float, line.split())
        poses.append(make_transform(quaternion_to_rotation(qx, qy, qz, qw), np.array([tx, ty, tz])))
    depths = []
    for i in range(1, 6):
        raw = cv2.imread(str(root / "depth" / f"{i}.pgm"), cv2.IMREAD_UNCHANGED)
        assert raw is not None and raw.dtype == np.uint16
        depths.append(raw.astype(np.float32) / float(meta["depth_scale"]))
    dets = json.loads((root / "detections_yolox_nano.json").read_text())["frames"]
    # Floor from all frames in the world frame; world "up" is roughly optical -y.
    cloud = np.concatenate([
        transform_points(T, backproject(d, K, *DEPTH_RANGE_M, stride_px=4)[0])
        for T, d in zip(poses, depths, strict=True)
    ])
    floor = estimate_floor(cloud, up_hint=np.array([0.0, -1.0, 0.0]), rng=np.random.default_rng(0))
    T_map_world = gravity_aligned_frame(floor.plane)
    T_map_cams = [T_map_world @ T for T in poses]

    classes = default_classes()
    by_name = {c.name: c for c in classes}
    omap = ObjectMap(classes)
    per_object: dict[int, list[ObjectObservation]] = {}
    rng = np.random.default_rng(0)
    for i, (d, T) in enumerate(zip(depths, T_map_cams, strict=True)):
        obs = []
        for j, det in enumerate(dets[f"{i + 1}.png"]):
            cls = COCO_TO_OURS.get(det["class"])
            if cls is None:
                continue
            # No tracker on five sparse frames: every box is a new track, so association
            # across frames is the map's footprint/class re-association.
            tr = Track(100 * i + j, tuple(det["xyxy"]), float(det["score"]), cls)
            o = observe_object(d, K, T, tr, by_name[cls], GeometryConfig(), depth_range_m=DEPTH_RANGE_M,
                               stamp_s=float(i), rng=rng)
            if o is not None:
                obs.append(o)
        ids = omap.update(obs, float(i), CameraView(d, K, T, DEPTH_RANGE_M))
        for o, oid in zip(obs, ids, strict=True):
            per_object.setdefault(oid, []).append(o)
    return {"K": K, "depths": depths, "T_map_cams": T_map_cams, "omap": omap, "per_object": per_object}


def test_floor_frame_puts_the_camera_at_a_plausible_height(scene) -> None:
    heights = [T[2, 3] for T in scene["T_map_cams"]]
    assert all(1.0 < h < 1.8 for h in heights)
    # Floor pixels of the first frame sit at z ~ 0 in the map frame.
    pts = transform_points(scene["T_map_cams"][0], backproject(scene["depths"][0], scene["K"], 0.3, 6.0, stride_px=4)[0])
    assert np.percentile(pts[:, 2], 2) > -0.08


def _table(scene):
    # COCO has one table class; which of ours it becomes is the geometric prior's choice.
    tables = [o for o in scene["omap"].objects()
              if o.class_name in ("desk", "coffee_table", "conference_table") and o.top_height_m is not None]
    assert tables, "the dining table did not become an object"
    return max(tables, key=lambda o: polygon_area_m2(o.footprint_xy_m))


def test_dining_table_height_and_footprint(scene) -> None:
    table = _table(scene)
    # The table's height is its top: the seat/top plane found by RANSAC.
    assert 0.65 <= table.top_height_m <= 0.85
    assert table.z_max_m >= table.top_height_m  # candles on it reach higher
    assert table.z_min_m == 0.0  # stands on the floor
    # Its footprint covers the space between its legs: a large area, most of which a depth
    # slice at leg height sees as empty.
    area = polygon_area_m2(table.footprint_xy_m)
    assert area > 1.0
    lo = table.footprint_xy_m.min(axis=0)
    hi = table.footprint_xy_m.max(axis=0)
    spec = GridSpec.covering(lo[0], lo[1], hi[0], hi[1], 0.05)
    inside = rasterize_polygon(spec, table.footprint_xy_m)
    T = scene["T_map_cams"][0]
    pts = transform_points(T, backproject(scene["depths"][0], scene["K"], 0.3, 6.0)[0])
    slice_pts = pts[(pts[:, 2] > 0.15) & (pts[:, 2] < 0.35)]
    rc = spec.cell_of(slice_pts[:, :2])
    ok = spec.contains_rc(rc)
    hit = np.zeros(spec.shape_rc, bool)
    hit[rc[ok, 0], rc[ok, 1]] = True
    assert (hit & inside).sum() < 0.5 * inside.sum()


def test_objects_seen_in_several_frames_agree_within_15_cm(scene) -> None:
    omap = scene["omap"]
    alive = {o.object_id: o for o in omap.objects()}
    multi = 0
    for oid, all_obs in scene["per_object"].items():
        # Views cut by the image border see part of the object: their centroid is elsewhere.
        observations = [o for o in all_obs if not o.at_image_edge]
        if oid not in alive or len({o.stamp_s for o in observations}) < 2:
            continue
        multi += 1
        pos = np.array([o.centroid_map_m[:2] for o in observations])
        fused = np.asarray(alive[oid].position_map_m[:2])
        assert np.linalg.norm(pos - fused, axis=1).max() <= 0.15, (alive[oid].class_name, pos, fused)
    assert multi >= 3  # the armchair and chairs seen from several poses


def test_chairs_seen_twice_are_confirmed_objects(scene) -> None:
    confirmed = scene["omap"].objects(confirmed_only=True)
    names = [o.class_name for o in confirmed]
    assert names.count("chair") >= 3
    assert all(0.3 < o.z_max_m < 1.5 for o in confirmed)
