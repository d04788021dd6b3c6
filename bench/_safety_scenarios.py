"""Safety-bench scenarios: a seeded furnished room, a flight altitude, and a start and goal whose
straight line crosses hollow-bottom furniture.

Two kinds, by altitude:

* ``blocking``: the furniture on the line reaches into the vehicle's band (e.g. a desk top or
  a chair seat at 0.6 m). A depth slice at that altitude sees only its legs; the semantic map
  knows the whole footprint.
* ``overflight``: the furniture on the line stays below the band (a coffee table or desk at
  1.5 m): the vehicle may fly straight over it, and a semantic map must not make it detour.

Start and goal are clear of every object's footprint (with the vehicle radius and the class
margin) and of walls, the start also for the vertical take-off, and the ideal semantic map
(ground truth) has a path between them for our planner, so every scenario can be flown. That
path must exist also with every object taller and wider by :data:`MAP_TOLERANCE_M` (the
object map's accuracy, ``bench/mapping.py``): a scenario whose only route is a passage a few
centimetres wider than the vehicle and its margins, or flies over a table top a few millimetres
below the band, is flyable only on a map better than any map we build.
Everything is in the room frame (interior ``[0, w] x [0, d]``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.config import CompanionConfig
from companion.sim.groundtruth import clearance_m, ground_truth_planner
from companion.sim.world import Room, generate_room
from planner.planner import Planner

#: Classes a depth slice sees only the legs (or posts, pedestal) of.
HOLLOW_CLASSES = ("chair", "coffee_table", "conference_table", "desk", "whiteboard")
TABLE_CLASSES = ("coffee_table", "conference_table", "desk")
#: The object map's accuracy the feasibility check allows for (metres): footprints grown and
#: height ranges widened by this. bench/mapping.py --section objects (seeds 1000-1019 and
#: 2000-2019): position error p95 0.042-0.044 m, height error p95 0.020-0.022 m (target 0.05).
MAP_TOLERANCE_M = 0.05


@dataclass(frozen=True)
class Scenario:
    """One room to fly twice (metric-only and semantic map)."""

    index: int
    room: Room
    altitude_m: float
    kind: str  # "blocking" or "overflight"
    start_xy_m: tuple[float, float]
    goal_xy_m: tuple[float, float]
    #: Objects the straight start-goal line passes over.
    crossed: tuple[tuple[int, str], ...]

    @property
    def distance_m(self) -> float:
        return math.dist(self.start_xy_m, self.goal_xy_m)


def _polygon_distance_m(poly: NDArray[np.float64], xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N,) signed distance of points to a polygon (negative inside)."""
    c = poly.astype(np.float32)
    return np.array([-cv2.pointPolygonTest(c, (float(x), float(y)), True) for x, y in xy])


def _crossed(room: Room, a: NDArray[np.float64], b: NDArray[np.float64]) -> list[int]:
    """Ids of objects whose footprint the segment a-b passes over."""
    n = max(2, int(math.ceil(np.linalg.norm(b - a) / 0.05)) + 1)
    pts = a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)
    return [o.object_id for o in room.objects if np.any(_polygon_distance_m(o.footprint_xy_m(), pts) <= 0.0)]


def pick_scenario(index: int, room: Room, cfg: CompanionConfig, altitude_m: float, kind: str,
                  rng: np.random.Generator, min_dist_m: float = 3.0, max_dist_m: float = 5.0,
                  tries: int = 600) -> Scenario | None:
    """A start and goal in ``room`` for ``kind`` at ``altitude_m`` (see the module doc), or None."""
    p = cfg.planner
    band = cfg.planner.band_at(altitude_m)
    margins = {c.name: c.margin_m for c in cfg.classes}
    hollow = [o for o in room.objects if o.class_name in HOLLOW_CLASSES]
    if kind == "blocking":
        targets = [o for o in hollow if band.intersects(*o.z_range_m)]
    else:
        targets = [o for o in hollow if not band.intersects(*o.z_range_m)]
    if not targets:
        return None
    by_id = {o.object_id: o for o in room.objects}
    # Tables and desks first (the reference design's case), chairs and whiteboards too.
    weights = np.array([3.0 if o.class_name in TABLE_CLASSES else 1.0 for o in targets])
    weights /= weights.sum()
    planner: Planner | None = None
    for _ in range(tries):
        target = targets[int(rng.choice(len(targets), p=weights))]
        centre = np.asarray(target.center_xy_m, dtype=np.float64)
        heading = rng.uniform(-math.pi, math.pi)
        u = np.array([math.cos(heading), math.sin(heading)])
        d = rng.uniform(min_dist_m, max_dist_m)
        f = rng.uniform(0.35, 0.65)
        a, b = centre - f * d * u, centre + (1.0 - f) * d * u
        ends = np.array([a, b])
        if np.any(ends < 0.45) or np.any(ends[:, 0] > room.width_m - 0.45) or np.any(ends[:, 1] > room.depth_m - 0.45):
            continue
        # Clear of every footprint (the semantic planner's radius + class margin + slack) and
        # of walls; the start also at every height up to the flight band (take-off).
        ok = True
        for o in room.objects:
            need = p.keepout_m(margins.get(o.class_name, 0.0)) + 0.15
            if np.any(_polygon_distance_m(o.footprint_xy_m(), ends) < need):
                ok = False
                break
        if not ok:
            continue
        start3 = np.array([[a[0], a[1], h] for h in np.arange(0.05, band.z_max_m + 0.05, 0.1)])
        if np.any(clearance_m(room, start3, 0.1) < p.keepout_m() + 0.15):
            continue
        goal3 = np.array([[b[0], b[1], altitude_m]])
        if np.any(clearance_m(room, goal3, band.z_max_m - band.z_min_m) < p.keepout_m() + 0.15):
            continue
        # The target must lie well ahead of the start: the camera sees it before it matters.
        if _polygon_distance_m(target.footprint_xy_m(), a[None])[0] < 0.8:
            continue
        crossed = _crossed(room, a, b)
        if target.object_id not in crossed:
            continue
        if planner is None:
            planner = ground_truth_planner(room, cfg, altitude_m=altitude_m, tolerance_m=MAP_TOLERANCE_M)
        if not planner.plan(a, b).ok:
            continue
        return Scenario(index, room, altitude_m, kind, (float(a[0]), float(a[1])), (float(b[0]), float(b[1])),
                        tuple((i, by_id[i].class_name) for i in crossed))
    return None


def make_scenarios(cfg: CompanionConfig, n_rooms: int, seed: int, altitudes_m: list[float],
                   width_m: float = 8.0, depth_m: float = 6.0, n_objects: int = 10,
                   layout: str = "realistic") -> list[Scenario]:
    """``n_rooms`` scenarios from room seeds ``seed, seed + 1, ...`` (a seed whose room has no
    fitting start and goal is skipped). Altitudes cycle through ``altitudes_m``; below 1 m the
    scenario is ``blocking`` (desks, tables, chair seats reach into the band), from 1 m up
    ``overflight`` (only whiteboards reach that high). ``layout``: :data:`companion.sim.world.LAYOUTS`."""
    out: list[Scenario] = []
    names = [c.name for c in cfg.classes]
    s = seed
    while len(out) < n_rooms and s < seed + 20 * n_rooms + 20:
        alt = altitudes_m[len(out) % len(altitudes_m)]
        kind = "blocking" if alt < 1.0 else "overflight"
        room = generate_room(s, width_m, depth_m, 2.6, n_objects, 2, class_names=names, layout=layout)
        sc = pick_scenario(len(out), room, cfg, alt, kind, np.random.default_rng(s))
        s += 1
        if sc is not None:
            out.append(sc)
    return out
