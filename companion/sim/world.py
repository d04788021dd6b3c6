"""Seeded generator of furnished rooms: the simulated world's geometry and ground truth.

Everything is built from oriented boxes (:class:`Box`) in the map frame (x east, y north, z up,
floor at z = 0). A room's interior spans ``[0, width_m] x [0, depth_m]``; walls stand outside
it, with doorway gaps. Furniture of the six classes is made of primitives with realistic
dimensions: legs, tops, seats, backs, panels. The space between legs is empty, which is the
whole point: a depth slice below the top sees only legs.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.errors import SimulationError

WALL_THICKNESS_M = 0.12
#: Room generators: furniture alone at random spots, or arranged as people arrange it.
LAYOUTS = ("realistic", "scattered")
DOOR_HEIGHT_M = 2.05


@dataclass(frozen=True)
class Box:
    """An oriented box: centre (x, y, z) m, size (along its x, along its y, z) m, yaw rad."""

    center_m: tuple[float, float, float]
    size_m: tuple[float, float, float]
    yaw_rad: float = 0.0

    @property
    def z_range_m(self) -> tuple[float, float]:
        return self.center_m[2] - self.size_m[2] / 2.0, self.center_m[2] + self.size_m[2] / 2.0

    def corners_xy_m(self) -> NDArray[np.float64]:
        """(4, 2) footprint corners, counter-clockwise."""
        hx, hy = self.size_m[0] / 2.0, self.size_m[1] / 2.0
        local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        R = np.array([[c, -s], [s, c]])
        return local @ R.T + np.array(self.center_m[:2])


@dataclass(frozen=True)
class FurnitureObject:
    """One piece of furniture: a class, an overall oriented extent, and its primitives.

    ``center_xy_m``/``yaw_rad``/``size_m`` describe the object's overall bounding box (length
    along its local x, width along local y, total height); ``parts`` are the boxes it is made
    of, already in the map frame.
    """

    object_id: int
    class_name: str
    center_xy_m: tuple[float, float]
    yaw_rad: float
    size_m: tuple[float, float, float]
    parts: tuple[Box, ...]
    color_rgb: tuple[int, int, int]

    @property
    def height_m(self) -> float:
        return max(p.z_range_m[1] for p in self.parts)

    @property
    def z_range_m(self) -> tuple[float, float]:
        return min(p.z_range_m[0] for p in self.parts), self.height_m

    def footprint_xy_m(self) -> NDArray[np.float64]:
        """(4, 2) oriented-rectangle footprint of the whole object (legs and the space between)."""
        return Box(
            (self.center_xy_m[0], self.center_xy_m[1], 0.0),
            (self.size_m[0], self.size_m[1], 0.0),
            self.yaw_rad,
        ).corners_xy_m()

    def footprint_distance_m(self, xy_m: NDArray[np.floating]) -> NDArray[np.float64]:
        """(N,) horizontal distance from (N, 2) points to :meth:`footprint_xy_m` (0 inside)."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        d = np.asarray(xy_m, dtype=np.float64).reshape(-1, 2) - np.asarray(self.center_xy_m)
        lx = np.abs(c * d[:, 0] + s * d[:, 1]) - self.size_m[0] / 2
        ly = np.abs(-s * d[:, 0] + c * d[:, 1]) - self.size_m[1] / 2
        return np.hypot(np.maximum(lx, 0.0), np.maximum(ly, 0.0))

    def centroid_m(self) -> NDArray[np.float64]:
        """Volume-weighted centroid of the primitives, (3,)."""
        vols = np.array([p.size_m[0] * p.size_m[1] * p.size_m[2] for p in self.parts])
        cents = np.array([p.center_m for p in self.parts])
        return (cents * vols[:, None]).sum(axis=0) / vols.sum()


@dataclass(frozen=True)
class Doorway:
    """A gap in a wall: ``center_xy_m`` on the wall line, ``width_m``, ``wall`` in S/E/N/W."""

    center_xy_m: tuple[float, float]
    width_m: float
    wall: str

    def inside_point_m(self, depth_m: float = 0.5) -> tuple[float, float]:
        """A point ``depth_m`` inside the room in front of the doorway."""
        dx, dy = {"S": (0.0, 1.0), "N": (0.0, -1.0), "W": (1.0, 0.0), "E": (-1.0, 0.0)}[self.wall]
        return self.center_xy_m[0] + dx * depth_m, self.center_xy_m[1] + dy * depth_m


@dataclass(frozen=True)
class Relation:
    """How a layout arranged two pieces: ``kind`` (e.g. ``chair_tucked``), object ``a_id``
    relative to ``b_id`` (0 = the nearest wall), and the spacing range it was drawn from."""

    kind: str
    a_id: int
    b_id: int
    range_m: tuple[float, float]


@dataclass(frozen=True)
class Room:
    """A generated room: walls, doorways and furniture.

    ``clutter`` holds solid things of none of our classes (cabinets, plants, monitors, cups):
    they are geometry the camera sees and the vehicle can hit, never ground-truth objects; their
    ids are negative. ``relations`` records how a realistic layout arranged the furniture.
    """

    seed: int
    width_m: float
    depth_m: float
    wall_height_m: float
    walls: tuple[Box, ...]
    doorways: tuple[Doorway, ...]
    objects: tuple[FurnitureObject, ...]
    floor_color_rgb: tuple[int, int, int] = (150, 130, 110)
    wall_color_rgb: tuple[int, int, int] = (215, 215, 205)
    clutter: tuple[FurnitureObject, ...] = ()
    relations: tuple[Relation, ...] = ()

    def all_boxes(self) -> list[tuple[Box, int]]:
        """Every primitive with its owner: object id, 0 for walls, negative for clutter."""
        out: list[tuple[Box, int]] = [(w, 0) for w in self.walls]
        for obj in (*self.objects, *self.clutter):
            out.extend((p, obj.object_id) for p in obj.parts)
        return out

    def object_by_id(self, object_id: int) -> FurnitureObject:
        for o in self.objects:
            if o.object_id == object_id:
                return o
        raise KeyError(object_id)


# --- furniture builders ---------------------------------------------------------------

def _place(parts_local: list[Box], cx: float, cy: float, yaw: float) -> tuple[Box, ...]:
    """Move boxes given in the object's local frame to the map frame."""
    c, s = math.cos(yaw), math.sin(yaw)
    out = []
    for b in parts_local:
        x, y, z = b.center_m
        out.append(Box((cx + c * x - s * y, cy + s * x + c * y, z), b.size_m, b.yaw_rad + yaw))
    return tuple(out)


def _legs(length: float, width: float, leg: float, height: float, inset: float) -> list[Box]:
    hx, hy = length / 2 - inset - leg / 2, width / 2 - inset - leg / 2
    return [Box((sx * hx, sy * hy, height / 2), (leg, leg, height)) for sx in (-1, 1) for sy in (-1, 1)]


def _chair(rng: np.random.Generator) -> tuple[tuple[float, float, float], list[Box]]:
    w = rng.uniform(0.42, 0.50)
    d = rng.uniform(0.42, 0.50)
    seat_h = rng.uniform(0.43, 0.48)
    back_h = rng.uniform(0.82, 0.95)
    t = 0.04
    parts = _legs(d, w, 0.035, seat_h - t, 0.0)
    parts.append(Box((0.0, 0.0, seat_h - t / 2), (d, w, t)))
    # Backrest along the rear edge (local -x), from the seat up.
    parts.append(Box((-d / 2 + 0.015, 0.0, (seat_h + back_h) / 2), (0.03, w, back_h - seat_h)))
    return (d, w, back_h), parts


def _table(
    rng: np.random.Generator, length: tuple[float, float], width: tuple[float, float],
    top: tuple[float, float], leg: float,
) -> tuple[tuple[float, float, float], list[Box], float]:
    L = rng.uniform(*length)
    W = rng.uniform(*width)
    H = rng.uniform(*top)
    t = 0.03
    parts = _legs(L, W, leg, H - t, 0.03)
    parts.append(Box((0.0, 0.0, H - t / 2), (L, W, t)))
    return (L, W, H), parts, t


def _desk(rng: np.random.Generator) -> tuple[tuple[float, float, float], list[Box]]:
    size, parts, _ = _table(rng, (1.2, 1.6), (0.6, 0.8), (0.72, 0.76), 0.05)
    return size, parts


def _coffee_table(rng: np.random.Generator) -> tuple[tuple[float, float, float], list[Box]]:
    size, parts, _ = _table(rng, (0.8, 1.2), (0.5, 0.7), (0.40, 0.48), 0.05)
    return size, parts


def _conference_table(rng: np.random.Generator) -> tuple[tuple[float, float, float], list[Box]]:
    L = rng.uniform(2.0, 3.0)
    W = rng.uniform(1.0, 1.3)
    H = rng.uniform(0.74, 0.76)
    t = 0.04
    # Partly hollow: a central panel pedestal carries the top; the rest overhangs.
    panel_L = L * rng.uniform(0.45, 0.6)
    parts = [
        Box((0.0, 0.0, H - t / 2), (L, W, t)),
        Box((0.0, 0.0, (H - t) / 2), (panel_L, 0.08, H - t)),
        Box((0.0, 0.0, 0.02), (panel_L, W * 0.5, 0.04)),  # the pedestal's foot
    ]
    return (L, W, H), parts


def _sofa(rng: np.random.Generator) -> tuple[tuple[float, float, float], list[Box]]:
    L = rng.uniform(1.6, 2.2)
    D = rng.uniform(0.8, 0.95)
    seat = rng.uniform(0.40, 0.45)
    back = rng.uniform(0.80, 0.90)
    arm = 0.18
    arm_h = rng.uniform(0.55, 0.65)
    back_d = 0.2
    # Solid to the floor: base, backrest, arms.
    parts = [
        Box((0.0, back_d / 2, seat / 2), (L - 2 * arm, D - back_d, seat)),
        Box((0.0, -D / 2 + back_d / 2, back / 2), (L, back_d, back)),
        Box((-L / 2 + arm / 2, back_d / 2, arm_h / 2), (arm, D - back_d, arm_h)),
        Box((L / 2 - arm / 2, back_d / 2, arm_h / 2), (arm, D - back_d, arm_h)),
    ]
    # Local axes: length along x, depth along y; the builder's size is (L, D, back).
    return (L, D, back), parts


def _whiteboard(rng: np.random.Generator) -> tuple[tuple[float, float, float], list[Box]]:
    W = rng.uniform(1.2, 1.8)
    bottom = rng.uniform(0.75, 0.85)
    top = rng.uniform(1.9, 2.05)
    foot = rng.uniform(0.5, 0.6)
    post = 0.04
    parts = [Box((0.0, 0.0, (bottom + top) / 2), (W, 0.03, top - bottom))]
    for sx in (-1, 1):
        x = sx * (W / 2 + post / 2)
        parts.append(Box((x, 0.0, top / 2), (post, post, top)))  # upright
        parts.append(Box((x, 0.0, 0.025), (post, foot, 0.05)))  # foot, within the footprint
    return (W + 2 * post, foot, top), parts


Builder = Callable[[np.random.Generator], tuple[tuple[float, float, float], list[Box]]]

BUILDERS: dict[str, Builder] = {
    "chair": _chair,
    "desk": _desk,
    "coffee_table": _coffee_table,
    "conference_table": _conference_table,
    "sofa": _sofa,
    "whiteboard": _whiteboard,
}

#: Relative frequency of each class in generated rooms (chairs are common).
CLASS_WEIGHTS: dict[str, float] = {
    "chair": 3.0, "desk": 1.5, "coffee_table": 1.0, "conference_table": 0.6, "sofa": 0.8,
    "whiteboard": 0.7,
}


def _palette(rng: np.random.Generator, class_name: str) -> tuple[int, int, int]:
    """A plausible furniture colour: woods, greys, fabrics; varied per object."""
    bases = {
        "chair": [(120, 80, 50), (40, 40, 45), (170, 40, 40), (60, 90, 140)],
        "desk": [(160, 120, 80), (200, 200, 195), (90, 70, 50)],
        "coffee_table": [(140, 100, 60), (60, 50, 40), (180, 170, 150)],
        "conference_table": [(110, 80, 55), (180, 180, 175)],
        "sofa": [(80, 90, 110), (150, 60, 50), (90, 110, 80), (200, 190, 170)],
        "whiteboard": [(245, 245, 245)],
    }[class_name]
    base = np.array(bases[int(rng.integers(len(bases)))], dtype=np.float64)
    jitter = rng.normal(0.0, 12.0, 3)
    return tuple(int(v) for v in np.clip(base + jitter, 0, 255))  # type: ignore[return-value]


# --- room generation ------------------------------------------------------------------

def _walls_with_doorways(
    width: float, depth: float, height: float, doorways: Sequence[Doorway]
) -> tuple[Box, ...]:
    """Four walls outside the interior, split around doorway gaps, with lintels above them."""
    t = WALL_THICKNESS_M
    walls: list[Box] = []
    spans = {
        "S": ((0.0 - t, width + t), -t / 2, True),
        "N": ((0.0 - t, width + t), depth + t / 2, True),
        "W": ((0.0, depth), -t / 2, False),
        "E": ((0.0, depth), width + t / 2, False),
    }
    for wall, ((a, b), offset, along_x) in spans.items():
        gaps = sorted(
            (d.center_xy_m[0] if along_x else d.center_xy_m[1], d.width_m)
            for d in doorways if d.wall == wall
        )
        cursor = a
        for c, w in [*gaps, (b + 1e9, 0.0)]:
            end = min(c - w / 2, b)
            if end - cursor > 1e-3:
                mid, length = (cursor + end) / 2, end - cursor
                walls.append(_wall_box(mid, offset, length, t, 0.0, height, along_x))
            if c < b:
                walls.append(_wall_box(c, offset, w, t, DOOR_HEIGHT_M, height, along_x))
                cursor = c + w / 2
    return tuple(walls)


def _wall_box(mid: float, offset: float, length: float, t: float, z0: float, z1: float,
              along_x: bool) -> Box:
    zc, zh = (z0 + z1) / 2, z1 - z0
    if along_x:
        return Box((mid, offset, zc), (length, t, zh))
    return Box((offset, mid, zc), (t, length, zh))


def _sample_doorways(rng: np.random.Generator, width: float, depth: float, n: int) -> list[Doorway]:
    walls = [str(w) for w in rng.permutation(["S", "N", "W", "E"])][:n]
    out = []
    for wall in walls:
        w = rng.uniform(0.9, 1.2)
        if wall in ("S", "N"):
            c = rng.uniform(0.3 + w / 2, width - 0.3 - w / 2)
            out.append(Doorway((c, 0.0 if wall == "S" else depth), w, wall))
        else:
            c = rng.uniform(0.3 + w / 2, depth - 0.3 - w / 2)
            out.append(Doorway((0.0 if wall == "W" else width, c), w, wall))
    return out


def _footprints_overlap(a: NDArray[np.float64], b: NDArray[np.float64], gap: float) -> bool:
    """Separating-axis test of two convex polygons, each grown by ``gap``/2."""
    for poly in (a, b):
        n = len(poly)
        for i in range(n):
            e = poly[(i + 1) % n] - poly[i]
            axis = np.array([-e[1], e[0]])
            axis /= np.linalg.norm(axis)
            pa, pb = a @ axis, b @ axis
            if pa.max() + gap / 2 < pb.min() - gap / 2 or pb.max() + gap / 2 < pa.min() - gap / 2:
                return False
    return True


def generate_room(
    seed: int,
    width_m: float = 8.0,
    depth_m: float = 6.0,
    wall_height_m: float = 2.6,
    n_objects: int = 8,
    n_doorways: int = 2,
    class_names: Sequence[str] | None = None,
    min_gap_m: float = 0.25,
    free_path_radius_m: float = 0.3,
    class_weights: Mapping[str, float] | None = None,
    layout: str = "scattered",
) -> Room:
    """A furnished room, the same for the same arguments.

    ``layout`` picks the generator: ``scattered`` (this function: every piece alone, at a random
    spot) or ``realistic`` (:func:`companion.sim.layouts.generate_realistic_room`: groups as
    people arrange them, touching walls and each other, with clutter); ``min_gap_m`` applies to
    ``scattered`` only.

    Classes are drawn with ``class_weights`` (relative; default :data:`CLASS_WEIGHTS`, where
    chairs are common); a class the mapping leaves out keeps its default weight.

    Objects are placed at random positions and yaws without overlapping each other (``min_gap_m``
    apart) or the walls. An object whose placement would block the last free path between the
    doorways (for a vehicle of ``free_path_radius_m`` at any height) is dropped and another
    tried, so a free path always exists. Raises :class:`SimulationError` for impossible sizes.
    """
    if layout not in LAYOUTS:
        raise SimulationError(f"unknown room layout {layout!r} (expected one of {list(LAYOUTS)})")
    if layout == "realistic":
        # Imported here: layouts builds on this module's types.
        from companion.sim.layouts import generate_realistic_room

        return generate_realistic_room(
            seed, width_m, depth_m, wall_height_m, n_objects, n_doorways, class_names=class_names,
            free_path_radius_m=free_path_radius_m, class_weights=class_weights)
    if width_m < 3.0 or depth_m < 3.0:
        raise SimulationError(f"room too small: {width_m} x {depth_m} m (minimum 3 x 3 m)")
    names = [n for n in (class_names or list(BUILDERS)) if n in BUILDERS]
    unknown = set(class_names or []) - set(BUILDERS)
    if unknown:
        raise SimulationError(f"no furniture builder for classes {sorted(unknown)}")
    rng = np.random.default_rng(seed)
    doorways = _sample_doorways(rng, width_m, depth_m, n_doorways)
    walls = _walls_with_doorways(width_m, depth_m, wall_height_m, doorways)
    unknown_w = set(class_weights or {}) - set(BUILDERS)
    if unknown_w:
        raise SimulationError(f"class_weights name classes with no furniture builder: {sorted(unknown_w)}")
    chosen = {**CLASS_WEIGHTS, **(class_weights or {})}
    bad = {n: w for n, w in chosen.items() if not (math.isfinite(w) and w >= 0.0)}
    if bad:
        raise SimulationError(f"class_weights must be finite and >= 0 (got {bad})")
    weights = np.array([chosen[n] for n in names])
    if weights.sum() <= 0.0:
        raise SimulationError(f"class_weights give every class of {names} weight 0")
    weights /= weights.sum()

    # Imported here: groundtruth depends on this module's types.
    from companion.sim.groundtruth import free_path_exists

    objects: list[FurnitureObject] = []
    attempts = 0
    keepout = [np.array([d.inside_point_m(0.0), d.inside_point_m(0.9)]) for d in doorways]
    while len(objects) < n_objects and attempts < n_objects * 60:
        attempts += 1
        cls = names[int(rng.choice(len(names), p=weights))]
        size, parts_local = BUILDERS[cls](rng)
        L, W = size[0], size[1]
        r = 0.5 * math.hypot(L, W)
        if 2 * r + 0.2 > min(width_m, depth_m):
            continue
        yaw = float(rng.uniform(-math.pi, math.pi))
        cx = float(rng.uniform(0.1 + r * 0.7, width_m - 0.1 - r * 0.7))
        cy = float(rng.uniform(0.1 + r * 0.7, depth_m - 0.1 - r * 0.7))
        parts = _place(parts_local, cx, cy, yaw)
        obj = FurnitureObject(
            object_id=len(objects) + 1, class_name=cls, center_xy_m=(cx, cy), yaw_rad=yaw,
            size_m=size, parts=parts, color_rgb=_palette(rng, cls),
        )
        fp = obj.footprint_xy_m()
        if fp[:, 0].min() < 0.05 or fp[:, 0].max() > width_m - 0.05:
            continue
        if fp[:, 1].min() < 0.05 or fp[:, 1].max() > depth_m - 0.05:
            continue
        if any(_footprints_overlap(fp, o.footprint_xy_m(), min_gap_m) for o in objects):
            continue
        if any(_segment_hits_polygon(seg, fp, free_path_radius_m) for seg in keepout):
            continue
        candidate = Room(seed, width_m, depth_m, wall_height_m, walls, tuple(doorways),
                         tuple([*objects, obj]))
        if len(doorways) >= 2 and not free_path_exists(candidate, free_path_radius_m):
            continue
        objects.append(obj)
    return Room(seed, width_m, depth_m, wall_height_m, walls, tuple(doorways), tuple(objects))


def _segment_hits_polygon(seg: NDArray[np.float64], poly: NDArray[np.float64], r: float) -> bool:
    """True if any sample of the segment lies within ``r`` of the polygon's bounding circle."""
    c = poly.mean(axis=0)
    rad = float(np.max(np.linalg.norm(poly - c, axis=1)))
    pts = seg[0] + np.linspace(0.0, 1.0, 10)[:, None] * (seg[1] - seg[0])
    return bool(np.any(np.linalg.norm(pts - c, axis=1) < rad + r))
