"""Furniture designs beyond the basic ones in :mod:`companion.sim.world`, and clutter.

Every builder returns a :class:`Design`: primitives in the object's local frame (length along
local x, width along local y, floor at z = 0) and what a room layout needs to arrange it: how
high the space under a table top is clear and how far a chair can slide under each edge.
Chairs face local +x (their back is at local -x); desks put their user at local -y.

Clutter (cabinets, plants, monitors, cups, ...) is built the same way but belongs to none of
our classes: it is solid geometry in the room, not a ground-truth object.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from companion.sim.world import BUILDERS, Box, _legs


@dataclass(frozen=True)
class Design:
    """One built piece: class, design name, overall size (local x, local y, height) and parts.

    ``tuck_m`` is how far a chair may slide under the long (local +-y) edges before its legs
    meet something of the table near the floor; ``tuck_end_m`` the same at the short edges;
    ``under_top_m`` the clear height under the top (0 for anything that is not a table).
    ``seat_m`` is a chair's seat height, ``tuckable`` whether it fits under a table at all.
    """

    class_name: str
    name: str
    size_m: tuple[float, float, float]
    parts: list[Box] = field(default_factory=list)
    tuck_m: float = 0.0
    tuck_end_m: float = 0.0
    under_top_m: float = 0.0
    seat_m: float = 0.0
    tuckable: bool = False


Rng = np.random.Generator

# --- chairs -------------------------------------------------------------------------------


def four_leg_chair(rng: Rng) -> Design:
    size, parts = BUILDERS["chair"](rng)
    seat = max(p.z_range_m[1] for p in parts if p.size_m[0] > 0.3 and p.size_m[2] < 0.1)
    return Design("chair", "four_leg_chair", size, parts, seat_m=seat, tuckable=True)


def office_chair(rng: Rng) -> Design:
    """Five-star base on a gas column, a padded seat and a backrest on a spine."""
    radius = rng.uniform(0.30, 0.34)
    seat_h = rng.uniform(0.44, 0.50)
    back_top = rng.uniform(0.90, 1.10)
    seat_d, seat_w = rng.uniform(0.44, 0.50), rng.uniform(0.46, 0.52)
    spin = rng.uniform(0.0, 2.0 * math.pi / 5.0)
    parts = []
    for k in range(5):
        a = spin + 2.0 * math.pi * k / 5.0
        parts.append(Box((0.5 * radius * math.cos(a), 0.5 * radius * math.sin(a), 0.06),
                         (radius, 0.05, 0.04), a))
        parts.append(Box((radius * math.cos(a), radius * math.sin(a), 0.03), (0.05, 0.05, 0.06), a))  # caster
    parts.append(Box((0.0, 0.0, (0.08 + seat_h - 0.07) / 2), (0.06, 0.06, seat_h - 0.07 - 0.08)))
    parts.append(Box((0.0, 0.0, seat_h - 0.035), (seat_d, seat_w, 0.07)))
    spine_x = -seat_d / 2 + 0.02
    parts.append(Box((spine_x, 0.0, seat_h + 0.06), (0.04, 0.06, 0.12)))
    parts.append(Box((spine_x - 0.01, 0.0, (seat_h + 0.12 + back_top) / 2),
                     (0.05, seat_w * 0.95, back_top - seat_h - 0.12)))
    span = 2.0 * radius + 0.08  # the casters stand out past the spokes' ends
    return Design("chair", "office_chair", (span, span, back_top), parts, seat_m=seat_h, tuckable=True)


def stool(rng: Rng) -> Design:
    """Four splayed-free legs, a square seat and a foot ring; no back."""
    s = rng.uniform(0.34, 0.40)
    seat_h = rng.uniform(0.44, 0.48)
    parts = _legs(s, s, 0.03, seat_h - 0.03, 0.0)
    parts.append(Box((0.0, 0.0, seat_h - 0.015), (s, s, 0.03)))
    ring_z = 0.22
    for sx in (-1, 1):
        parts.append(Box((sx * (s / 2 - 0.015), 0.0, ring_z), (0.02, s - 0.03, 0.02)))
        parts.append(Box((0.0, sx * (s / 2 - 0.015), ring_z), (s - 0.03, 0.02, 0.02)))
    return Design("chair", "stool", (s, s, seat_h), parts, seat_m=seat_h, tuckable=True)


def armchair(rng: Rng) -> Design:
    """Upholstered and solid to the floor: seat block, back and two arms (does not tuck)."""
    d, w = rng.uniform(0.75, 0.88), rng.uniform(0.72, 0.86)
    seat_h, back_h, arm_h, arm = rng.uniform(0.40, 0.45), rng.uniform(0.80, 0.95), rng.uniform(0.58, 0.66), 0.15
    back_d = 0.18
    parts = [
        Box((back_d / 2, 0.0, seat_h / 2), (d - back_d, w - 2 * arm, seat_h)),
        Box((-d / 2 + back_d / 2, 0.0, back_h / 2), (back_d, w, back_h)),
        Box((back_d / 2, -w / 2 + arm / 2, arm_h / 2), (d - back_d, arm, arm_h)),
        Box((back_d / 2, w / 2 - arm / 2, arm_h / 2), (d - back_d, arm, arm_h)),
    ]
    return Design("chair", "armchair", (d, w, back_h), parts, seat_m=seat_h)


# --- tables and desks ------------------------------------------------------------------------


def _top(L: float, W: float, H: float, t: float) -> Box:
    return Box((0.0, 0.0, H - t / 2), (L, W, t))


def leg_table(rng: Rng, cls: str, length: tuple[float, float], width: tuple[float, float],
              height: tuple[float, float]) -> Design:
    L, W, H, t = rng.uniform(*length), rng.uniform(*width), rng.uniform(*height), 0.03
    parts = [*_legs(L, W, 0.05, H - t, 0.03), _top(L, W, H, t)]
    return Design(cls, "leg_table", (L, W, H), parts, tuck_m=W / 2 - 0.02, tuck_end_m=L / 2 - 0.1,
                  under_top_m=H - t)


def apron_table(rng: Rng, cls: str, length: tuple[float, float], width: tuple[float, float],
                height: tuple[float, float]) -> Design:
    """Four legs joined under the top by an apron (a frame of boards)."""
    L, W, H, t = rng.uniform(*length), rng.uniform(*width), rng.uniform(*height), 0.03
    a = rng.uniform(0.07, 0.10)
    inset = 0.05
    z = H - t - a / 2
    parts = [*_legs(L, W, 0.055, H - t, inset), _top(L, W, H, t)]
    for s in (-1, 1):
        parts.append(Box((0.0, s * (W / 2 - inset - 0.01), z), (L - 2 * inset, 0.02, a)))
        parts.append(Box((s * (L / 2 - inset - 0.01), 0.0, z), (0.02, W - 2 * inset, a)))
    return Design(cls, "apron_table", (L, W, H), parts, tuck_m=W / 2 - 0.02, tuck_end_m=L / 2 - 0.1,
                  under_top_m=H - t - a)


def pedestal_table(rng: Rng, cls: str, length: tuple[float, float], width: tuple[float, float],
                   height: tuple[float, float]) -> Design:
    """One central column on a cross foot carries the top."""
    L, W, H, t = rng.uniform(*length), rng.uniform(*width), rng.uniform(*height), 0.03
    foot = min(L, W) * rng.uniform(0.55, 0.7)
    parts = [
        _top(L, W, H, t),
        Box((0.0, 0.0, (H - t) / 2), (0.12, 0.12, H - t)),
        Box((0.0, 0.0, 0.02), (foot, 0.08, 0.04)),
        Box((0.0, 0.0, 0.02), (0.08, foot, 0.04)),
    ]
    return Design(cls, "pedestal_table", (L, W, H), parts, tuck_m=W / 2 - foot / 2 - 0.02,
                  tuck_end_m=L / 2 - foot / 2 - 0.02, under_top_m=H - t)


def panel_conference_table(rng: Rng) -> Design:
    size, parts = BUILDERS["conference_table"](rng)
    L, W, H = size
    panel_l = max(p.size_m[0] for p in parts if p.size_m[1] < 0.1)
    foot_w = max(p.size_m[1] for p in parts if p.size_m[2] < 0.05)
    return Design("conference_table", "panel_table", size, parts, tuck_m=W / 2 - foot_w / 2 - 0.02,
                  tuck_end_m=L / 2 - panel_l / 2 - 0.02, under_top_m=H - 0.04)


def trestle_desk(rng: Rng) -> Design:
    """Two solid end panels and a modesty panel along the back (local +y) under the top."""
    L, W, H, t = rng.uniform(1.2, 1.6), rng.uniform(0.6, 0.8), rng.uniform(0.72, 0.76), 0.03
    panel_t = 0.03
    modesty_h = rng.uniform(0.30, 0.45)
    parts = [_top(L, W, H, t)]
    for s in (-1, 1):
        parts.append(Box((s * (L / 2 - 0.04), 0.0, (H - t) / 2), (panel_t, W - 0.06, H - t)))
    parts.append(Box((0.0, W / 2 - 0.06, H - t - modesty_h / 2), (L - 0.1, 0.02, modesty_h)))
    return Design("desk", "trestle_desk", (L, W, H), parts, tuck_m=W - 0.12, tuck_end_m=0.0,
                  under_top_m=H - t)


#: Size ranges (length, width, height) per table class.
TABLE_SIZES: dict[str, tuple[tuple[float, float], tuple[float, float], tuple[float, float]]] = {
    "desk": ((1.2, 1.6), (0.6, 0.8), (0.72, 0.76)),
    "coffee_table": ((0.8, 1.2), (0.5, 0.7), (0.40, 0.48)),
    "conference_table": ((2.0, 3.0), (1.0, 1.3), (0.74, 0.76)),
    "dining_table": ((1.5, 2.0), (0.85, 1.0), (0.74, 0.77)),
}


def table(rng: Rng, cls: str, size_key: str | None = None) -> Design:
    """A table of class ``cls`` in one of its designs, sized as ``size_key`` (default ``cls``)."""
    dims = TABLE_SIZES[size_key or cls]
    options: list[Callable[[], Design]] = [
        lambda: leg_table(rng, cls, *dims), lambda: apron_table(rng, cls, *dims),
    ]
    if cls == "desk":
        options.append(lambda: trestle_desk(rng))
    elif cls == "conference_table" and size_key is None:
        options.append(lambda: panel_conference_table(rng))
    else:
        options.append(lambda: pedestal_table(rng, cls, *dims))
    return options[int(rng.integers(len(options)))]()


# --- other classes -------------------------------------------------------------------------


def sofa(rng: Rng) -> Design:
    size, parts = BUILDERS["sofa"](rng)
    return Design("sofa", "sofa", size, parts)


def standing_whiteboard(rng: Rng) -> Design:
    size, parts = BUILDERS["whiteboard"](rng)
    return Design("whiteboard", "standing_whiteboard", size, parts)


def wall_whiteboard(rng: Rng) -> Design:
    """A board hung on the wall: nothing below it reaches the floor."""
    W, bottom, top = rng.uniform(1.2, 2.0), rng.uniform(0.85, 0.95), rng.uniform(1.95, 2.1)
    return Design("whiteboard", "wall_whiteboard", (W, 0.03, top),
                  [Box((0.0, 0.0, (bottom + top) / 2), (W, 0.03, top - bottom))])


# --- clutter --------------------------------------------------------------------------------


def cabinet(rng: Rng) -> Design:
    tall = rng.random() < 0.4
    W, D = rng.uniform(0.5, 1.0), rng.uniform(0.4, 0.6)
    H = rng.uniform(1.7, 2.0) if tall else rng.uniform(0.75, 1.1)
    return Design("cabinet", "cabinet", (W, D, H), [Box((0.0, 0.0, H / 2), (W, D, H))])


def shelf(rng: Rng) -> Design:
    """A bookshelf: solid sides, back and shelves; seen from the side it is a solid block."""
    W, D, H = rng.uniform(0.6, 1.0), rng.uniform(0.28, 0.38), rng.uniform(1.2, 2.0)
    parts = [Box((0.0, D / 2 - 0.01, H / 2), (W, 0.02, H))]
    for s in (-1, 1):
        parts.append(Box((s * (W / 2 - 0.01), 0.0, H / 2), (0.02, D, H)))
    n = max(2, int(H / 0.35))
    for k in range(n + 1):
        parts.append(Box((0.0, 0.0, 0.01 + k * (H - 0.02) / n), (W - 0.04, D, 0.02)))
        if k < n and rng.random() < 0.8:  # books on the shelf
            bh = rng.uniform(0.15, 0.28)
            parts.append(Box((0.0, 0.02, 0.02 + k * (H - 0.02) / n + bh / 2), (W * rng.uniform(0.4, 0.9), D - 0.06, bh)))
    return Design("shelf", "shelf", (W, D, H), parts)


def plant(rng: Rng) -> Design:
    pot, pot_h, crown, h = rng.uniform(0.25, 0.35), rng.uniform(0.25, 0.40), rng.uniform(0.4, 0.7), rng.uniform(0.9, 1.6)
    return Design("plant", "plant", (crown, crown, h), [
        Box((0.0, 0.0, pot_h / 2), (pot, pot, pot_h)),
        Box((0.0, 0.0, (pot_h + h) / 2), (crown * 0.7, crown * 0.7, h - pot_h), rng.uniform(0, 1.5)),
        Box((0.0, 0.0, pot_h + 0.6 * (h - pot_h)), (crown, crown, 0.5 * (h - pot_h))),
    ])


def floor_lamp(rng: Rng) -> Design:
    h, shade = rng.uniform(1.5, 1.8), rng.uniform(0.3, 0.45)
    return Design("floor_lamp", "floor_lamp", (shade, shade, h), [
        Box((0.0, 0.0, 0.015), (0.3, 0.3, 0.03)),
        Box((0.0, 0.0, h / 2), (0.03, 0.03, h - 0.05)),
        Box((0.0, 0.0, h - 0.13), (shade, shade, 0.26)),
    ])


def boxes(rng: Rng) -> Design:
    """One to three cardboard boxes stacked."""
    parts, z, size = [], 0.0, rng.uniform(0.35, 0.6)
    for _ in range(int(rng.integers(1, 4))):
        h = rng.uniform(0.25, 0.45)
        parts.append(Box((rng.uniform(-0.03, 0.03), rng.uniform(-0.03, 0.03), z + h / 2),
                         (size, size * rng.uniform(0.7, 1.0), h), rng.uniform(-0.2, 0.2)))
        z += h
        size *= rng.uniform(0.75, 0.95)
    return Design("box", "boxes", (parts[0].size_m[0] + 0.1, parts[0].size_m[0] + 0.1, z), parts)


def monitor(rng: Rng) -> Design:
    w, h = rng.uniform(0.5, 0.7), rng.uniform(0.30, 0.42)
    base_z = rng.uniform(0.08, 0.14)
    return Design("monitor", "monitor", (w, 0.22, base_z + h), [
        Box((0.0, 0.0, 0.01), (0.22, 0.2, 0.02)),
        Box((0.0, 0.03, (base_z + 0.1) / 2), (0.05, 0.03, base_z + 0.1)),
        Box((0.0, 0.0, base_z + h / 2), (w, 0.03, h)),
    ])


def laptop(rng: Rng) -> Design:
    w, d = rng.uniform(0.30, 0.36), rng.uniform(0.21, 0.25)
    return Design("laptop", "laptop", (w, d, d), [
        Box((0.0, 0.0, 0.01), (w, d, 0.02)),
        Box((0.0, d / 2, 0.02 + d * 0.45), (w, 0.01, d * 0.9)),
    ])


def books(rng: Rng) -> Design:
    w, d, h = rng.uniform(0.15, 0.24), rng.uniform(0.21, 0.30), rng.uniform(0.03, 0.18)
    return Design("books", "books", (w, d, h), [Box((0.0, 0.0, h / 2), (w, d, h), rng.uniform(-0.3, 0.3))])


def cup(rng: Rng) -> Design:
    s, h = rng.uniform(0.07, 0.09), rng.uniform(0.08, 0.12)
    return Design("cup", "cup", (s, s, h), [Box((0.0, 0.0, h / 2), (s, s, h))])


def vase(rng: Rng) -> Design:
    s, h = rng.uniform(0.10, 0.18), rng.uniform(0.22, 0.45)
    return Design("vase", "vase", (s, s, h), [Box((0.0, 0.0, h / 2), (s, s, h), rng.uniform(0, 1.5))])


def desk_lamp(rng: Rng) -> Design:
    h = rng.uniform(0.35, 0.5)
    return Design("desk_lamp", "desk_lamp", (0.2, 0.2, h), [
        Box((0.0, 0.0, 0.01), (0.16, 0.16, 0.02)),
        Box((0.0, 0.0, h / 2), (0.025, 0.025, h - 0.05)),
        Box((0.05, 0.0, h - 0.05), (0.16, 0.12, 0.1)),
    ])


#: Clutter standing on the floor, and clutter that stands on tables and desks.
FLOOR_CLUTTER: dict[str, Callable[[Rng], Design]] = {
    "cabinet": cabinet, "shelf": shelf, "plant": plant, "floor_lamp": floor_lamp, "box": boxes,
}
TABLETOP_CLUTTER: dict[str, Callable[[Rng], Design]] = {
    "monitor": monitor, "laptop": laptop, "books": books, "cup": cup, "vase": vase, "desk_lamp": desk_lamp,
}
#: Clutter whose surfaces read as dark or shiny to an active-stereo camera (screens, glazing).
SHINY_CLUTTER = frozenset({"monitor", "laptop", "vase"})
CLUTTER_COLORS: dict[str, list[tuple[int, int, int]]] = {
    "cabinet": [(200, 200, 195), (120, 90, 60), (60, 60, 65)],
    "shelf": [(150, 110, 70), (230, 230, 225), (40, 35, 30)],
    "plant": [(50, 110, 45), (70, 130, 60)],
    "floor_lamp": [(30, 30, 30), (220, 215, 200)],
    "box": [(170, 130, 85)],
    "monitor": [(15, 15, 18)],
    "laptop": [(120, 120, 125), (25, 25, 28)],
    "books": [(150, 40, 40), (40, 70, 130), (200, 180, 120)],
    "cup": [(240, 240, 235), (60, 60, 140)],
    "vase": [(90, 140, 160), (180, 60, 40)],
    "desk_lamp": [(25, 25, 25), (200, 200, 200)],
}
