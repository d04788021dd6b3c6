"""The seeded room generator and its ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.errors import SimulationError
from companion.sim.groundtruth import (
    clearance_m,
    free_path_exists,
    occupancy_at_band,
    room_grid_spec,
    semantic_costmap,
)
from companion.sim.world import BUILDERS, DOOR_HEIGHT_M, Box, FurnitureObject, Room, generate_room
from semmap.costmap import LETHAL_OBSTACLE, VerticalBand
from semmap.grid import GridSpec, rasterize_polygon


def footprint_masks(room: Room, resolution_m: float = 0.02) -> list[np.ndarray]:
    spec = GridSpec.covering(0.0, 0.0, room.width_m, room.depth_m, resolution_m)
    return [rasterize_polygon(spec, o.footprint_xy_m()) for o in room.objects]


def check_room_invariants(room: Room) -> None:
    masks = footprint_masks(room)
    # No two footprints share a cell (the generator keeps 0.25 m between them; a 2 cm grid
    # dilates each by 1 cm).
    if masks:
        assert int(np.max(np.sum(masks, axis=0))) <= 1
    for obj in room.objects:
        fp = obj.footprint_xy_m()
        assert fp[:, 0].min() >= 0.0 and fp[:, 0].max() <= room.width_m
        assert fp[:, 1].min() >= 0.0 and fp[:, 1].max() <= room.depth_m
        # Every primitive lies within the object's footprint and stands on (or above) the floor.
        for part in obj.parts:
            c, s = math.cos(obj.yaw_rad), math.sin(obj.yaw_rad)
            d = part.corners_xy_m() - np.asarray(obj.center_xy_m)
            lx, ly = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
            assert np.all(np.abs(lx) <= obj.size_m[0] / 2 + 1e-6), (obj.class_name, part)
            assert np.all(np.abs(ly) <= obj.size_m[1] / 2 + 1e-6), (obj.class_name, part)
            assert part.z_range_m[0] >= -1e-9
        assert obj.z_range_m[0] == pytest.approx(0.0)
        assert obj.height_m == pytest.approx(obj.size_m[2])
    if len(room.doorways) >= 2:
        assert free_path_exists(room, 0.3)


@pytest.mark.parametrize("seed", range(6))
def test_default_rooms_are_valid(seed: int) -> None:
    room = generate_room(seed)
    assert len(room.objects) == 8 and len(room.doorways) == 2
    check_room_invariants(room)


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 10**6), width=st.floats(3.0, 12.0), depth=st.floats(3.0, 12.0),
    n_objects=st.integers(0, 14), n_doorways=st.integers(1, 4),
)
def test_any_room_is_valid(seed: int, width: float, depth: float, n_objects: int, n_doorways: int) -> None:
    room = generate_room(seed, width, depth, n_objects=n_objects, n_doorways=n_doorways)
    assert len(room.objects) <= n_objects and len(room.doorways) == n_doorways
    assert [o.object_id for o in room.objects] == list(range(1, len(room.objects) + 1))
    check_room_invariants(room)


def test_same_seed_same_room_and_different_seeds_differ() -> None:
    a, b = generate_room(42), generate_room(42)
    assert a == b
    c = generate_room(43)
    assert c != a
    assert [o.center_xy_m for o in a.objects] != [o.center_xy_m for o in c.objects]


def objects_of(cls: str, n: int = 200) -> list[FurnitureObject]:
    """``n`` objects of a class straight from its builder (local frame, at the origin)."""
    out = []
    for seed in range(n):
        size, parts = BUILDERS[cls](np.random.default_rng(seed))
        out.append(FurnitureObject(seed + 1, cls, (0.0, 0.0), 0.0, size, tuple(parts), (0, 0, 0)))
    return out


def test_placed_objects_keep_their_builders_dimensions() -> None:
    for obj in generate_room(3, n_objects=8).objects:
        assert obj.height_m == pytest.approx(obj.size_m[2])
        area = sum(p.size_m[0] * p.size_m[1] for p in obj.parts)
        assert area > 0


def widest_horizontal(obj: FurnitureObject) -> Box:
    return max(obj.parts, key=lambda p: p.size_m[0] * p.size_m[1])


def test_chair_dimensions() -> None:
    for chair in objects_of("chair"):
        seat = widest_horizontal(chair)
        assert 0.42 <= seat.z_range_m[1] <= 0.49  # seat height
        assert 0.8 <= chair.height_m <= 0.96  # backrest top
        assert 0.4 <= chair.size_m[0] <= 0.52 and 0.4 <= chair.size_m[1] <= 0.52
        legs = [p for p in chair.parts if p.z_range_m[0] == 0.0]
        assert len(legs) == 4 and all(p.size_m[0] < 0.06 for p in legs)


@pytest.mark.parametrize(
    ("cls", "top_range_m", "length_range_m"),
    [("desk", (0.72, 0.76), (1.2, 1.6)), ("coffee_table", (0.40, 0.48), (0.8, 1.2)),
     ("conference_table", (0.74, 0.76), (2.0, 3.0))],
)
def test_table_dimensions(cls: str, top_range_m: tuple[float, float], length_range_m: tuple[float, float]) -> None:
    for t in objects_of(cls):
        top = max(t.parts, key=lambda p: p.z_range_m[1])
        assert top_range_m[0] - 1e-9 <= top.z_range_m[1] <= top_range_m[1] + 1e-9
        assert length_range_m[0] <= t.size_m[0] <= length_range_m[1]
        assert top.size_m[2] <= 0.05  # a thin top


def test_whiteboard_board_spans_the_usual_heights() -> None:
    for wb in objects_of("whiteboard"):
        board = max(wb.parts, key=lambda p: p.size_m[0] * p.size_m[2])
        z0, z1 = board.z_range_m
        assert 0.75 <= z0 <= 0.85 and 1.9 <= z1 <= 2.05
        assert 0.8 <= z1 - z0 <= 2.0 and board.size_m[1] < 0.05


def test_sofa_is_solid_to_the_floor() -> None:
    for sofa in objects_of("sofa"):
        assert 0.8 <= sofa.height_m <= 0.9
        assert all(p.z_range_m[0] == 0.0 for p in sofa.parts)


@pytest.mark.parametrize(("cls", "hollow"), [("chair", True), ("desk", True), ("coffee_table", True),
                                             ("sofa", False)])
def test_a_low_slice_sees_only_legs_of_hollow_furniture(cls: str, hollow: bool) -> None:
    room = generate_room(5, 10, 8, n_objects=6, class_names=[cls])
    spec = room_grid_spec(room, 0.02)
    slice_occ = occupancy_at_band(room, spec, VerticalBand(0.15, 0.25))
    for obj in room.objects:
        fp = rasterize_polygon(spec, obj.footprint_xy_m())
        seen = np.count_nonzero(slice_occ & fp) / np.count_nonzero(fp)
        assert (seen < 0.2) if hollow else (seen > 0.6), (cls, seen)


def test_semantic_costmap_blocks_whole_footprints_but_the_slice_does_not() -> None:
    room = generate_room(2, n_objects=8, class_names=["desk", "chair"])
    spec = room_grid_spec(room, 0.05)
    band = VerticalBand.for_altitude(0.25, 0.1, 0.05)  # below seats and table tops
    cm = semantic_costmap(room, spec, band, class_names=["chair", "desk"])
    slice_occ = occupancy_at_band(room, spec, band)
    for obj in room.objects:
        fp = rasterize_polygon(spec, obj.footprint_xy_m())
        assert np.all(cm.cost[fp] == LETHAL_OBSTACLE)
        assert np.all(cm.class_index[fp] == ["chair", "desk"].index(obj.class_name))
        assert np.count_nonzero(slice_occ & fp) < np.count_nonzero(fp)


def test_doorways_are_gaps_with_a_lintel() -> None:
    room = generate_room(0)
    for d in room.doorways:
        x, y = d.center_xy_m
        # At head height in the doorway's centre: nothing within half the door width.
        c = clearance_m(room, np.array([[x, y, 1.0]]), vehicle_height_m=0.2, include_walls=True)[0]
        assert c >= d.width_m / 2 - 1e-6
        # Above the door: the lintel.
        assert clearance_m(room, np.array([[x, y, DOOR_HEIGHT_M + 0.2]]), 0.1)[0] < 0.1


def test_free_path_check_detects_a_blocked_room() -> None:
    room = generate_room(0, 6.0, 4.0, n_objects=0, n_doorways=2)
    assert free_path_exists(room, 0.3)
    # A floor-to-ceiling partition across the whole room separates the doorways (if they are
    # on opposite sides of it) or not; build one that cuts between them.
    (a, b) = room.doorways
    ax, ay = a.inside_point_m(0.6)
    bx, by = b.inside_point_m(0.6)
    if abs(ax - bx) >= abs(ay - by):
        xm = (ax + bx) / 2
        wall = Box((xm, room.depth_m / 2, 1.3), (0.1, room.depth_m, 2.6))
    else:
        ym = (ay + by) / 2
        wall = Box((room.width_m / 2, ym, 1.3), (room.width_m, 0.1, 2.6))
    blocker = FurnitureObject(1, "sofa", (wall.center_m[0], wall.center_m[1]), 0.0, wall.size_m, (wall,), (0, 0, 0))
    blocked = Room(room.seed, room.width_m, room.depth_m, room.wall_height_m, room.walls, room.doorways, (blocker,))
    assert not free_path_exists(blocked, 0.3)


def test_impossible_requests_raise() -> None:
    with pytest.raises(SimulationError, match="too small"):
        generate_room(0, 2.0, 5.0)
    with pytest.raises(SimulationError, match="piano"):
        generate_room(0, class_names=["chair", "piano"])
    assert set(BUILDERS) == {"chair", "desk", "coffee_table", "conference_table", "sofa", "whiteboard"}
