"""Rooms furnished as people furnish them (``sim.layout: realistic``).

Furniture comes in groups, each arranged with real-world spacing and recorded as
:class:`~companion.sim.world.Relation` s:

* dining and conference sets: a table with 4-10 chairs facing it, each pushed in (seat under
  the top, footprints overlapping by :data:`TUCK_M`) or pulled out (:data:`PULLED_OUT_M` from
  the edge); conference tables have chairs on both long sides, sometimes a free-standing
  whiteboard :data:`WHITEBOARD_NEAR_TABLE_M` beyond one end;
* a desk with its back against a wall (:data:`AGAINST_WALL_M`), an office chair in front,
  partly under it (:data:`DESK_TUCK_M`) or pulled out, and a monitor, laptop, books on it;
* a sofa against a wall with a coffee table :data:`COFFEE_TABLE_GAP_M` in front of it;
* whiteboards on a wall or standing against it; single chairs;
* clutter of none of our classes: cabinets and shelves against walls and in corners, plants,
  floor lamps, boxes; monitors, laptops, books, cups, vases on tables and desks.

Groups go against walls and into corners or free in the room; between groups stays a walkway,
and a group that would close the last free path between the doorways (at any height, for a
vehicle of ``free_path_radius_m``) is not placed. Ground truth stays per object: each object's
own footprint and height, even where a tucked chair's footprint overlaps its table's.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from companion.errors import SimulationError
from companion.sim import furniture as fu
from companion.sim.world import (
    BUILDERS,
    CLASS_WEIGHTS,
    Box,
    FurnitureObject,
    Relation,
    Room,
    _footprints_overlap,
    _palette,
    _place,
    _sample_doorways,
    _segment_hits_polygon,
    _walls_with_doorways,
)

#: Spacing ranges (metres) of each relation kind; the test of 200 rooms checks them.
TUCK_M = (0.10, 0.35)  # chair footprint under the table's
DESK_TUCK_M = (0.10, 0.30)  # office chair under the desk
PULLED_OUT_M = (0.05, 0.40)  # chair front to the table edge
COFFEE_TABLE_GAP_M = (0.30, 0.50)  # sofa front to coffee table
ARMCHAIR_GAP_M = (0.25, 0.50)  # armchair front to coffee table
AGAINST_WALL_M = (0.0, 0.03)  # back of a desk, sofa, whiteboard, cabinet to its wall
WHITEBOARD_NEAR_TABLE_M = (0.6, 1.2)  # standing whiteboard to a conference table's end
RANGES: dict[str, tuple[float, float]] = {
    "chair_tucked": TUCK_M, "chair_at_desk_tucked": DESK_TUCK_M, "chair_pulled_out": PULLED_OUT_M,
    "coffee_table_front": COFFEE_TABLE_GAP_M, "armchair_front": ARMCHAIR_GAP_M,
    "against_wall": AGAINST_WALL_M, "whiteboard_near_table": WHITEBOARD_NEAR_TABLE_M,
}
#: Clear walkway between groups (metres).
GROUP_GAP_M = 0.35
#: Relative frequency of each group (the class weights scale them by their main class).
GROUP_WEIGHTS: dict[str, float] = {
    "dining": 1.0, "conference": 0.7, "desk": 1.6, "lounge": 1.0, "whiteboard": 0.6, "chair": 0.5,
}
GROUP_MAIN_CLASS = {
    "dining": "conference_table", "conference": "conference_table", "desk": "desk",
    "lounge": "sofa", "whiteboard": "whiteboard", "chair": "chair",
}


@dataclass
class _Piece:
    """One member of a group, posed in the group's frame (wall side towards local +y)."""

    design: fu.Design
    xy_m: tuple[float, float]
    yaw_rad: float
    z0_m: float = 0.0
    clutter: bool = False
    #: Relations to other members by index in the group (b = -1: the wall).
    relations: list[tuple[str, int]] = field(default_factory=list)

    def footprint(self) -> NDArray[np.float64]:
        L, W = self.design.size_m[0], self.design.size_m[1]
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        local = np.array([[-L / 2, -W / 2], [L / 2, -W / 2], [L / 2, W / 2], [-L / 2, W / 2]])
        return local @ np.array([[c, -s], [s, c]]).T + np.asarray(self.xy_m)


def _rot(v: tuple[float, float], yaw: float) -> tuple[float, float]:
    c, s = math.cos(yaw), math.sin(yaw)
    return c * v[0] - s * v[1], s * v[0] + c * v[1]


def _extent_along(design: fu.Design, rel_yaw: float) -> float:
    """Half-extent of a design's footprint along a direction at ``rel_yaw`` to its local x."""
    return design.size_m[0] / 2 * abs(math.cos(rel_yaw)) + design.size_m[1] / 2 * abs(math.sin(rel_yaw))


def _chair_at_edge(rng: np.random.Generator, chair: fu.Design, table: _Piece, side: str, along_m: float,
                   tuck_range: tuple[float, float], tuck_kind: str, p_tuck: float, table_index: int) -> _Piece:
    """A chair facing the table from ``side`` (+y, -y, +x, -x of the table), ``along_m`` along
    that edge: pushed in (footprint overlap in ``tuck_range``) when it fits, else pulled out."""
    L, W = table.design.size_m[0], table.design.size_m[1]
    normal = {"+y": (0.0, 1.0), "-y": (0.0, -1.0), "+x": (1.0, 0.0), "-x": (-1.0, 0.0)}[side]
    half = W / 2 if side in ("+y", "-y") else L / 2
    limit = table.design.tuck_m if side in ("+y", "-y") else table.design.tuck_end_m
    fits = chair.tuckable and chair.seat_m < table.design.under_top_m - 0.02
    hi = min(tuck_range[1], limit, chair.size_m[0] - 0.08)
    tucked = fits and hi >= tuck_range[0] and rng.random() < p_tuck
    jitter = rng.uniform(-0.04, 0.04) if tucked else rng.uniform(-0.2, 0.2)
    # The chair faces -normal (its local +x points at the table).
    facing = math.atan2(-normal[1], -normal[0]) + jitter
    ext = _extent_along(chair, jitter)
    offset = half + ext - rng.uniform(tuck_range[0], hi) if tucked else half + ext + rng.uniform(*PULLED_OUT_M)
    tangent = (-normal[1], normal[0])
    local = (normal[0] * offset + tangent[0] * along_m, normal[1] * offset + tangent[1] * along_m)
    gx, gy = _rot(local, table.yaw_rad)
    piece = _Piece(chair, (table.xy_m[0] + gx, table.xy_m[1] + gy), facing + table.yaw_rad)
    piece.relations.append((tuck_kind if tucked else "chair_pulled_out", table_index))
    return piece


def _slots(length_m: float, pitch_m: float, n_max: int) -> list[float]:
    n = max(0, min(n_max, int((length_m - 0.15) // pitch_m)))
    return [(k + 0.5) * (length_m - 0.15) / n - (length_m - 0.15) / 2 for k in range(n)] if n else []


def _tabletop(rng: np.random.Generator, table: _Piece, kinds: Sequence[tuple[str, float]],
              back_y_m: float | None = None) -> list[_Piece]:
    """Clutter standing on a table's top: each kind with its probability, not overlapping."""
    L, W, H = table.design.size_m
    out: list[_Piece] = []
    for kind, p in kinds:
        if rng.random() >= p:
            continue
        d = fu.TABLETOP_CLUTTER[kind](rng)
        for _ in range(6):
            hx, hy = d.size_m[0] / 2 + 0.03, d.size_m[1] / 2 + 0.03
            if hx >= L / 2 or hy >= W / 2:
                break
            lx = rng.uniform(-L / 2 + hx, L / 2 - hx)
            ly = W / 2 - hy if kind == "monitor" and back_y_m is not None else rng.uniform(-W / 2 + hy, W / 2 - hy)
            gx, gy = _rot((lx, ly), table.yaw_rad)
            yaw = table.yaw_rad + (0.0 if kind in ("monitor", "laptop") else rng.uniform(-0.4, 0.4))
            if kind == "laptop":
                yaw += math.pi  # lid away from the user, towards the table's +y
            cand = _Piece(d, (table.xy_m[0] + gx, table.xy_m[1] + gy), yaw, z0_m=H, clutter=True)
            if not any(_footprints_overlap(cand.footprint(), o.footprint(), 0.02) for o in out):
                out.append(cand)
                break
    return out


# --- groups (each in its own frame; the side that may go against a wall is local +y) ---------

def _table_set(rng: np.random.Generator, conference: bool, allow: set[str]) -> list[_Piece]:
    design = fu.table(rng, "conference_table") if conference else fu.table(rng, "conference_table", "dining_table")
    table = _Piece(design, (0.0, 0.0), 0.0)
    pieces = [table]
    if "chair" in allow:
        if conference:
            chair_fn = fu.office_chair if rng.random() < 0.6 else fu.four_leg_chair
        else:
            chair_fn = fu.four_leg_chair if rng.random() < 0.75 else fu.stool
        proto = chair_fn(rng)
        pitch = max(proto.size_m[1], proto.size_m[0] if proto.name == "office_chair" else 0.0) + 0.12
        L, W = design.size_m[0], design.size_m[1]
        p_tuck = rng.uniform(0.4, 0.9)
        for side in ("+y", "-y"):
            for x in _slots(L, pitch, 4 if conference else 3):
                pieces.append(_chair_at_edge(rng, chair_fn(rng), table, side, -x if side == "-y" else x,
                                             TUCK_M, "chair_tucked", p_tuck, 0))
        ends = [s for s in ("+x", "-x") if rng.random() < (0.5 if conference else 0.7)]
        for side in ends:
            if W >= pitch:
                pieces.append(_chair_at_edge(rng, chair_fn(rng), table, side, 0.0, TUCK_M, "chair_tucked", p_tuck, 0))
        if conference and "whiteboard" in allow and rng.random() < 0.4 and "+x" not in ends:
            wb = fu.standing_whiteboard(rng)
            gap = rng.uniform(*WHITEBOARD_NEAR_TABLE_M)
            wb_piece = _Piece(wb, (L / 2 + gap + wb.size_m[1] / 2, 0.0), math.pi / 2)
            wb_piece.relations.append(("whiteboard_near_table", 0))
            pieces.append(wb_piece)
    pieces = _drop_colliding(pieces)
    kinds = [("laptop", 0.4), ("books", 0.4), ("cup", 0.6), ("vase", 0.4), ("cup", 0.3)]
    return pieces + _tabletop(rng, table, kinds)


def _drop_colliding(pieces: list[_Piece]) -> list[_Piece]:
    """Drop chairs whose footprint overlaps an earlier chair's (corners of a table)."""
    kept: list[_Piece] = []
    for p in pieces:
        if p.design.class_name == "chair" and any(
                k.design.class_name == "chair" and _footprints_overlap(p.footprint(), k.footprint(), 0.02)
                for k in kept):
            continue
        kept.append(p)
    return kept


def _desk_set(rng: np.random.Generator, allow: set[str]) -> list[_Piece]:
    desk = _Piece(fu.table(rng, "desk"), (0.0, 0.0), 0.0)
    desk.relations.append(("against_wall", -1))
    pieces = [desk]
    if "chair" in allow:
        chair = fu.office_chair(rng) if rng.random() < 0.8 else fu.four_leg_chair(rng)
        room_x = desk.design.size_m[0] / 2 - chair.size_m[1] / 2 - 0.1
        along = rng.uniform(-room_x, room_x) if room_x > 0 else 0.0
        pieces.append(_chair_at_edge(rng, chair, desk, "-y", -along, DESK_TUCK_M, "chair_at_desk_tucked",
                                     0.65, 0))
    kinds = [("monitor", 0.8), ("laptop", 0.5), ("books", 0.5), ("cup", 0.6), ("desk_lamp", 0.4)]
    return pieces + _tabletop(rng, desk, kinds, back_y_m=desk.design.size_m[1] / 2)


def _lounge(rng: np.random.Generator, allow: set[str]) -> list[_Piece]:
    pieces: list[_Piece] = []
    front_y = 0.0
    if "sofa" in allow:
        s = fu.sofa(rng)
        sofa = _Piece(s, (0.0, 0.0), math.pi)  # backrest towards +y (the wall)
        sofa.relations.append(("against_wall", -1))
        pieces.append(sofa)
        front_y = -s.size_m[1] / 2
    if "coffee_table" in allow:
        ct = fu.table(rng, "coffee_table")
        gap = rng.uniform(*COFFEE_TABLE_GAP_M) if pieces else 0.4
        table = _Piece(ct, (0.0, front_y - gap - ct.size_m[1] / 2), 0.0)
        if pieces:
            table.relations.append(("coffee_table_front", 0))
        t_index = len(pieces)
        pieces.append(table)
        if "chair" in allow and rng.random() < 0.6:
            arm = fu.armchair(rng)
            side = 1.0 if rng.random() < 0.5 else -1.0
            g = rng.uniform(*ARMCHAIR_GAP_M)
            x = side * (ct.size_m[0] / 2 + g + arm.size_m[0] / 2)
            chair = _Piece(arm, (x, table.xy_m[1]), 0.0 if side < 0 else math.pi)
            chair.relations.append(("armchair_front", t_index))
            pieces.append(chair)
        pieces += _tabletop(rng, table, [("books", 0.5), ("cup", 0.5), ("vase", 0.4)])
    if pieces and "sofa" in allow and rng.random() < 0.5:
        lamp = fu.floor_lamp(rng)
        x = (pieces[0].design.size_m[0] / 2 + lamp.size_m[0] / 2 + 0.05) * (1 if rng.random() < 0.5 else -1)
        pieces.append(_Piece(lamp, (x, -lamp.size_m[1] / 2 + 0.2), 0.0, clutter=True))
    return pieces


def _whiteboard(rng: np.random.Generator) -> list[_Piece]:
    d = fu.wall_whiteboard(rng) if rng.random() < 0.5 else fu.standing_whiteboard(rng)
    p = _Piece(d, (0.0, 0.0), 0.0)
    p.relations.append(("against_wall", -1))
    return [p]


def _lone_chair(rng: np.random.Generator) -> list[_Piece]:
    d = [fu.four_leg_chair, fu.office_chair, fu.stool, fu.armchair][int(rng.integers(4))](rng)
    return [_Piece(d, (0.0, 0.0), -math.pi / 2 + rng.uniform(-0.3, 0.3))]  # back to the wall side


def _floor_clutter(rng: np.random.Generator) -> list[_Piece]:
    kind = str(rng.choice(["cabinet", "shelf", "plant", "floor_lamp", "box"], p=[0.3, 0.25, 0.2, 0.1, 0.15]))
    return [_Piece(fu.FLOOR_CLUTTER[kind](rng), (0.0, 0.0), 0.0, clutter=True)]


# --- placement --------------------------------------------------------------------------------

#: Group yaw that turns its local +y towards each wall.
_WALL_YAW = {"N": 0.0, "S": math.pi, "W": math.pi / 2, "E": -math.pi / 2}


def _posed(pieces: list[_Piece], x: float, y: float, yaw: float, at_wall: bool = True) -> list[_Piece]:
    out = []
    for p in pieces:
        gx, gy = _rot(p.xy_m, yaw)
        rels = [r for r in p.relations if at_wall or r[0] != "against_wall"]
        out.append(_Piece(p.design, (x + gx, y + gy), p.yaw_rad + yaw, p.z0_m, p.clutter, rels))
    return out


def _pose_group(rng: np.random.Generator, pieces: list[_Piece], width: float, depth: float,
                at_wall: bool) -> list[_Piece]:
    """The group moved into the room: its +y side flush against a random wall (sometimes into a
    corner), or free with a yaw mostly square to the walls."""
    fps = np.concatenate([p.footprint() for p in pieces if p.z0_m == 0.0])
    (x0, y0), (x1, y1) = fps.min(axis=0), fps.max(axis=0)
    if not at_wall:
        yaw = float(rng.integers(4)) * math.pi / 2 + (rng.normal(0.0, 0.05) if rng.random() < 0.8 else rng.uniform(-math.pi, math.pi))
        r = 0.5 * math.hypot(x1 - x0, y1 - y0)
        cx, cy = -(x0 + x1) / 2, -(y0 + y1) / 2
        px, py = rng.uniform(r * 0.6, max(r * 0.6, width - r * 0.6)), rng.uniform(r * 0.6, max(r * 0.6, depth - r * 0.6))
        ox, oy = _rot((cx, cy), yaw)
        return _posed(pieces, px + ox, py + oy, yaw, at_wall=False)
    wall = str(rng.choice(["N", "S", "W", "E"]))
    yaw = _WALL_YAW[wall]
    gap = rng.uniform(*AGAINST_WALL_M)
    span = width if wall in ("N", "S") else depth
    lo, hi = -x0, span - x1  # where the group's local x = 0 may go along the wall
    if hi < lo:
        return []
    u = lo if rng.random() < 0.15 else hi if rng.random() < 0.18 else rng.uniform(lo, hi)
    u += rng.uniform(0.0, 0.03) if u == lo else -rng.uniform(0.0, 0.03) if u == hi else 0.0
    # Local (u along the wall, back edge at the wall) to the room frame.
    if wall == "N":
        return _posed(pieces, u, depth - gap - y1, yaw)
    if wall == "S":
        return _posed(pieces, width - u, gap + y1, yaw)
    if wall == "W":
        return _posed(pieces, gap + y1, u, yaw)
    return _posed(pieces, width - gap - y1, depth - u, yaw)


def _inside(fp: NDArray[np.float64], width: float, depth: float) -> bool:
    return bool(fp[:, 0].min() >= -1e-6 and fp[:, 1].min() >= -1e-6
                and fp[:, 0].max() <= width + 1e-6 and fp[:, 1].max() <= depth + 1e-6)


def _objects(pieces: list[_Piece], first_id: int, first_clutter: int,
             rng: np.random.Generator) -> tuple[list[FurnitureObject], list[FurnitureObject], list[Relation]]:
    objs: list[FurnitureObject] = []
    clutter: list[FurnitureObject] = []
    rels: list[Relation] = []
    ids: list[int] = []
    n_obj, n_clut = first_id, first_clutter
    for p in pieces:
        if p.clutter:
            ids.append(n_clut)
            n_clut -= 1
        else:
            ids.append(n_obj)
            n_obj += 1
    for p, oid in zip(pieces, ids, strict=True):
        parts = _place([_raise(b, p.z0_m) for b in p.design.parts], p.xy_m[0], p.xy_m[1], p.yaw_rad)
        if p.clutter:
            colors = fu.CLUTTER_COLORS[p.design.class_name]
            base = np.array(colors[int(rng.integers(len(colors)))], dtype=np.float64)
            color = tuple(int(v) for v in np.clip(base + rng.normal(0.0, 8.0, 3), 0, 255))
        else:
            color = _palette(rng, p.design.class_name)
        obj = FurnitureObject(oid, p.design.class_name, p.xy_m, p.yaw_rad, p.design.size_m, parts,
                              color)  # type: ignore[arg-type]
        (clutter if p.clutter else objs).append(obj)
        for kind, j in p.relations:
            rels.append(Relation(kind, oid, 0 if j < 0 else ids[j], RANGES[kind]))
    return objs, clutter, rels


def _raise(b: Box, dz: float) -> Box:
    return Box((b.center_m[0], b.center_m[1], b.center_m[2] + dz), b.size_m, b.yaw_rad) if dz else b


def generate_realistic_room(
    seed: int,
    width_m: float = 8.0,
    depth_m: float = 6.0,
    wall_height_m: float = 2.6,
    n_objects: int = 8,
    n_doorways: int = 2,
    class_names: Sequence[str] | None = None,
    free_path_radius_m: float = 0.3,
    class_weights: Mapping[str, float] | None = None,
) -> Room:
    """A room furnished with groups (see the module doc), the same for the same arguments.

    Groups are added until the room holds about ``n_objects`` objects of our classes (a group
    that would overshoot sheds pulled-out chairs, or is not placed) or no more fit; then floor
    clutter. Classes not in ``class_names`` are left out of every group; ``class_weights``
    scale how often each group's main class comes (a table set's main class is
    ``conference_table``).
    """
    if width_m < 3.0 or depth_m < 3.0:
        raise SimulationError(f"room too small: {width_m} x {depth_m} m (minimum 3 x 3 m)")
    unknown = set(class_names or []) - set(BUILDERS)
    if unknown:
        raise SimulationError(f"no furniture builder for classes {sorted(unknown)}")
    unknown_w = set(class_weights or {}) - set(BUILDERS)
    if unknown_w:
        raise SimulationError(f"class_weights name classes with no furniture builder: {sorted(unknown_w)}")
    chosen = {**CLASS_WEIGHTS, **(class_weights or {})}
    bad = {n: w for n, w in chosen.items() if not (math.isfinite(w) and w >= 0.0)}
    if bad:
        raise SimulationError(f"class_weights must be finite and >= 0 (got {bad})")
    # A class of weight 0 is left out of every group (a table set without chairs).
    allow = {c for c in (class_names or BUILDERS) if chosen[c] > 0.0}
    kinds = [k for k in GROUP_WEIGHTS if GROUP_MAIN_CLASS[k] in allow
             or (k == "lounge" and "coffee_table" in allow)]
    weights = np.array([GROUP_WEIGHTS[k] * chosen[GROUP_MAIN_CLASS[k]] / CLASS_WEIGHTS[GROUP_MAIN_CLASS[k]]
                        if GROUP_MAIN_CLASS[k] in allow else GROUP_WEIGHTS[k] for k in kinds])
    if n_objects > 0 and (not kinds or weights.sum() <= 0.0):
        raise SimulationError(f"class_weights give every class of {sorted(allow)} weight 0")

    from companion.sim.groundtruth import free_path_exists

    rng = np.random.default_rng([seed, 31337])
    doorways = _sample_doorways(rng, width_m, depth_m, n_doorways)
    walls = _walls_with_doorways(width_m, depth_m, wall_height_m, doorways)
    keepout = [np.array([d.inside_point_m(0.0), d.inside_point_m(0.9)]) for d in doorways]
    objects: list[FurnitureObject] = []
    clutter: list[FurnitureObject] = []
    relations: list[Relation] = []
    placed_fps: list[NDArray[np.float64]] = []

    def try_place(pieces: list[_Piece], at_wall: bool) -> bool:
        posed = _pose_group(rng, pieces, width_m, depth_m, at_wall)
        if not posed:
            return False
        fps = [p.footprint() for p in posed]
        for p, fp in zip(posed, fps, strict=True):
            if not _inside(fp, width_m, depth_m):
                return False
            if p.z0_m == 0.0 and any(_footprints_overlap(fp, o, GROUP_GAP_M) for o in placed_fps):
                return False
            if any(_segment_hits_polygon(seg, fp, free_path_radius_m) for seg in keepout):
                return False
        objs, clut, rels = _objects(posed, len(objects) + 1, -len(clutter) - 1, rng)
        cand = Room(seed, width_m, depth_m, wall_height_m, walls, tuple(doorways), tuple(objects + objs),
                    clutter=tuple(clutter + clut))
        if len(doorways) >= 2 and not free_path_exists(cand, free_path_radius_m):
            return False
        objects.extend(objs)
        clutter.extend(clut)
        relations.extend(rels)
        placed_fps.extend(fp for p, fp in zip(posed, fps, strict=True) if p.z0_m == 0.0)
        return True

    attempts = 0
    while n_objects > 0 and len(objects) < n_objects and attempts < 40:
        attempts += 1
        kind = kinds[int(rng.choice(len(kinds), p=weights / weights.sum()))]
        pieces = _build_group(rng, kind, allow)
        pieces = _fit_budget(pieces, n_objects - len(objects))
        if not pieces:
            continue
        at_wall = kind in ("desk", "whiteboard") or (kind == "lounge" and rng.random() < 0.85) \
            or (kind == "chair" and rng.random() < 0.5)
        for _ in range(8):
            if try_place(pieces, at_wall):
                break
    if n_objects > 0:
        n_clutter = int(rng.integers(2, 4 + int(width_m * depth_m / 16.0)))
        for _ in range(n_clutter):
            pieces = _floor_clutter(rng)
            for _ in range(6):
                if try_place(pieces, rng.random() < 0.85):
                    break
    return Room(seed, width_m, depth_m, wall_height_m, walls, tuple(doorways), tuple(objects),
                clutter=tuple(clutter), relations=tuple(relations))


def _build_group(rng: np.random.Generator, kind: str, allow: set[str]) -> list[_Piece]:
    if kind in ("dining", "conference"):
        return _table_set(rng, kind == "conference", allow)
    if kind == "desk":
        return _desk_set(rng, allow)
    if kind == "lounge":
        return _lounge(rng, allow)
    if kind == "whiteboard":
        return _whiteboard(rng)
    return _lone_chair(rng)


def _fit_budget(pieces: list[_Piece], budget: int) -> list[_Piece]:
    """Shed pulled-out chairs (then any chairs, keeping at least four at a table) until the
    group's objects fit ``budget``; [] when it cannot."""
    def count(ps: list[_Piece]) -> int:
        return sum(not p.clutter for p in ps)

    if count(pieces) <= budget:
        return pieces
    if len(pieces) >= 2 and pieces[0].design.class_name == "conference_table":
        chairs = [i for i, p in enumerate(pieces) if p.design.class_name == "chair"]
        order = sorted(chairs, key=lambda i: pieces[i].relations[0][0] != "chair_pulled_out")
        drop: set[int] = set()
        for i in order:
            if count(pieces) - len(drop) <= budget or len(chairs) - len(drop) <= 4:
                break
            drop.add(i)
        kept = [p for i, p in enumerate(pieces) if i not in drop]
        if count(kept) <= budget:
            return kept
    return []
