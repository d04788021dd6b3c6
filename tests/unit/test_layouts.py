"""Realistic room layouts: groups with their real-world spacing, exact ground truth per object,
and a free path through every doorway (200 generated rooms)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.errors import SimulationError
from companion.sim.groundtruth import (
    free_path_exists,
    interior_mask,
    occupancy_at_band,
    room_grid_spec,
)
from companion.sim.layouts import RANGES
from companion.sim.world import BUILDERS, FurnitureObject, Room, _footprints_overlap, generate_room
from semmap.costmap import VerticalBand

TABLES = ("desk", "conference_table", "coffee_table")


def _rooms(n: int) -> list[Room]:
    out = []
    for seed in range(n):
        rng = np.random.default_rng(seed)
        out.append(generate_room(
            seed, width_m=float(rng.uniform(5.0, 10.0)), depth_m=float(rng.uniform(4.0, 8.0)),
            n_objects=int(rng.integers(6, 15)), n_doorways=int(rng.integers(1, 4)), layout="realistic"))
    return out


@pytest.fixture(scope="module")
def rooms() -> list[Room]:
    return _rooms(200)


def _penetration_m(chair: FurnitureObject, table: FurnitureObject) -> float:
    """How far the chair's footprint reaches past the table edge it stands at (< 0: a gap)."""
    c, s = math.cos(table.yaw_rad), math.sin(table.yaw_rad)
    d = chair.footprint_xy_m() - np.asarray(table.center_xy_m)
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)
    centre = local.mean(axis=0)
    half = np.array(table.size_m[:2]) / 2
    axis = int(np.argmax(np.abs(centre) - half))
    sign = 1.0 if centre[axis] > 0 else -1.0
    return float(half[axis] - np.min(sign * local[:, axis]))


def _polygon_gap_m(a: FurnitureObject, b: FurnitureObject) -> float:
    return float(min(b.footprint_distance_m(a.footprint_xy_m()).min(), a.footprint_distance_m(b.footprint_xy_m()).min()))


def _wall_gap_m(room: Room, a: FurnitureObject) -> float:
    fp = a.footprint_xy_m()
    return float(min(fp[:, 0].min(), fp[:, 1].min(), room.width_m - fp[:, 0].max(), room.depth_m - fp[:, 1].max()))


def _measure_m(room: Room, kind: str, a: FurnitureObject, b: FurnitureObject | None) -> float:
    if kind == "against_wall":
        return _wall_gap_m(room, a)
    assert b is not None
    if kind in ("chair_tucked", "chair_at_desk_tucked"):
        return _penetration_m(a, b)
    if kind == "chair_pulled_out":
        return -_penetration_m(a, b)
    return _polygon_gap_m(a, b)


def test_every_relation_is_within_its_stated_spacing(rooms: list[Room]) -> None:
    seen: dict[str, int] = {}
    for room in rooms:
        for rel in room.relations:
            a = room.object_by_id(rel.a_id)
            b = room.object_by_id(rel.b_id) if rel.b_id else None
            got = _measure_m(room, rel.kind, a, b)
            lo, hi = RANGES[rel.kind]
            assert lo - 1e-6 <= got <= hi + 1e-6, (room.seed, rel, got)
            seen[rel.kind] = seen.get(rel.kind, 0) + 1
    # Every arrangement turns up in 200 rooms, most of them many times.
    assert set(seen) == set(RANGES), seen
    assert min(seen.values()) >= 5, seen


def test_a_third_of_the_chairs_stand_partly_under_a_table_or_desk(rooms: list[Room]) -> None:
    n_chairs = n_under = 0
    for room in rooms:
        tables = [o for o in room.objects if o.class_name in TABLES]
        for chair in (o for o in room.objects if o.class_name == "chair"):
            n_chairs += 1
            n_under += any(_footprints_overlap(chair.footprint_xy_m(), t.footprint_xy_m(), -0.02) for t in tables)
    assert n_chairs > 400
    assert n_under >= n_chairs / 3, (n_under, n_chairs)


def test_table_sets_have_four_to_ten_chairs_facing_the_table(rooms: list[Room]) -> None:
    n_sets = 0
    for room in rooms:
        chairs_of: dict[int, list[int]] = {}
        for rel in room.relations:
            if rel.kind in ("chair_tucked", "chair_pulled_out") and room.object_by_id(rel.b_id).class_name == "conference_table":
                chairs_of.setdefault(rel.b_id, []).append(rel.a_id)
        for table_id, chair_ids in chairs_of.items():
            n_sets += 1
            assert 4 <= len(chair_ids) <= 10, (room.seed, table_id, chair_ids)
            table = room.object_by_id(table_id)
            for cid in chair_ids:
                chair = room.object_by_id(cid)
                to_table = np.asarray(table.center_xy_m) - np.asarray(chair.center_xy_m)
                facing = np.array([math.cos(chair.yaw_rad), math.sin(chair.yaw_rad)])
                # Facing the table: its front points at the table's near half, not away.
                assert float(facing @ to_table) > 0.0, (room.seed, cid)
    assert n_sets >= 30


def test_a_free_path_through_every_doorway(rooms: list[Room]) -> None:
    for room in rooms:
        assert free_path_exists(room, 0.3), room.seed
        spec = room_grid_spec(room, 0.1)
        occ = occupancy_at_band(room, spec, VerticalBand(0.0, room.wall_height_m))
        free = ~occ & interior_mask(room, spec)
        for d in room.doorways:
            r, c = spec.cell_of(np.array([d.inside_point_m(0.6)]))[0]
            assert free[r, c], (room.seed, d)


def test_ground_truth_is_per_object_and_clutter_is_not_an_object(rooms: list[Room]) -> None:
    for room in rooms[:60]:
        for obj in room.objects:
            assert obj.object_id > 0 and obj.class_name in BUILDERS
            corners = np.concatenate([p.corners_xy_m() for p in obj.parts])
            assert float(obj.footprint_distance_m(corners).max()) < 0.01, (room.seed, obj.object_id)
            assert obj.height_m == pytest.approx(obj.size_m[2], abs=0.01), (room.seed, obj.object_id)
        for c in room.clutter:
            assert c.object_id < 0 and c.class_name not in BUILDERS
        owners = {oid for _, oid in room.all_boxes()}
        assert {c.object_id for c in room.clutter} <= owners


def test_tabletop_clutter_raises_some_tables_highest_point_above_the_top(rooms: list[Room]) -> None:
    raised = 0
    for room in rooms[:60]:
        for t in (o for o in room.objects if o.class_name in TABLES):
            above = [c for c in room.clutter if t.footprint_distance_m(np.array([c.center_xy_m]))[0] == 0.0
                     and c.z_range_m[0] >= t.height_m - 0.01]
            raised += bool(above)
    assert raised >= 20


def test_same_seed_same_room_and_classes_left_out_stay_out() -> None:
    a, b = generate_room(7, layout="realistic"), generate_room(7, layout="realistic")
    assert a == b
    only = generate_room(7, n_objects=10, class_names=["desk", "chair"], layout="realistic")
    assert {o.class_name for o in only.objects} <= {"desk", "chair"}
    assert generate_room(7, n_objects=0, layout="realistic").objects == ()


def test_unknown_layout_is_named() -> None:
    with pytest.raises(SimulationError, match="layout 'tidy'"):
        generate_room(0, layout="tidy")


def test_clutter_is_seen_but_is_never_an_object_in_the_masks() -> None:
    pytest.importorskip("open3d")
    from companion.config import CompanionConfig
    from companion.sim.d455 import exact_depth
    from companion.sim.render import RoomRenderer
    from semmap.frames import R_BODY_CAMERA_FORWARD, make_transform, pose_from_xyz_rpy
    from semmap.types import CameraIntrinsics

    room = next(r for r in (generate_room(s, layout="realistic") for s in range(20))
                if any(c.class_name == "monitor" for c in r.clutter))
    monitor = next(c for c in room.clutter if c.class_name == "monitor")
    names = [c.name for c in CompanionConfig().classes]
    r = RoomRenderer(room, names, CameraIntrinsics(191.5, 191.5, 160.0, 120.0, 320, 240), noise=exact_depth())
    # Look at the monitor from 1.2 m, at its height.
    mx, my = monitor.center_xy_m
    ang = monitor.yaw_rad - math.pi / 2  # in front of the screen, where the user sits
    cx, cy = mx + 1.2 * math.cos(ang), my + 1.2 * math.sin(ang)
    T = pose_from_xyz_rpy(cx, cy, monitor.z_range_m[1] - 0.15, 0.0, 0.0, math.atan2(my - cy, mx - cx)) @ make_transform(
        R_BODY_CAMERA_FORWARD, np.zeros(3))
    frame = r.render(T)
    inst, cls = np.asarray(frame.masks["instance"]), np.asarray(frame.masks["class"])
    assert np.count_nonzero(inst == monitor.object_id) > 200
    assert np.all(cls[inst < 0] == -1)
    assert all(v.object_id > 0 for v in r.visible_objects(frame))
