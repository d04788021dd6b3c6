"""The planner on a room's true map (companion/sim/groundtruth.py): what a mission or a
safety scenario may ask of our map, allowing for the map's error."""

from __future__ import annotations

import numpy as np

from companion.config import CompanionConfig
from companion.sim.groundtruth import densify, ground_truth_planner
from companion.sim.world import Box, FurnitureObject, Room

#: Two sofas across the room, 0.5 m high, leaving one passage between x = 2.6 and x_gap_end.
SOFA_H = 0.5


def _sofa(object_id: int, x0: float, x1: float) -> FurnitureObject:
    cx, w = (x0 + x1) / 2, x1 - x0
    return FurnitureObject(object_id, "sofa", (cx, 2.0), 0.0, (w, 0.8, SOFA_H),
                           (Box((cx, 2.0, SOFA_H / 2), (w, 0.8, SOFA_H)),), (90, 90, 90))


def _floor_lamp(x: float, y: float) -> FurnitureObject:
    """A 0.4 m round base on the floor and a thin pole up to a shade at 1.6 m."""
    parts = (Box((x, y, 0.015), (0.4, 0.4, 0.03)), Box((x, y, 0.8), (0.03, 0.03, 1.6)),
             Box((x, y, 1.5), (0.4, 0.4, 0.2)))
    return FurnitureObject(-1, "floor_lamp", (x, y), 0.0, (0.4, 0.4, 1.6), parts, (200, 200, 200))


def _room(gap_m: float, clutter: tuple[FurnitureObject, ...] = ()) -> Room:
    """A 6 x 4 m room cut in two across y = 2 by two sofas with a ``gap_m`` passage at x = 3."""
    return Room(1, 6.0, 4.0, 2.6, (), (),
                (_sofa(1, 0.0, 3.0 - gap_m / 2), _sofa(2, 3.0 + gap_m / 2, 6.0)), clutter=clutter)


def _cfg() -> CompanionConfig:
    cfg = CompanionConfig()
    return cfg.model_copy(update={"planner": cfg.planner.model_copy(update={"flight_altitude_m": 0.6})})


def _needed_gap_m(cfg: CompanionConfig) -> float:
    sofa = next(c for c in cfg.classes if c.name == "sofa")
    return 2 * cfg.planner.keepout_m(sofa.margin_m)


def test_a_passage_a_perfect_map_allows_is_refused_with_the_map_error_allowed_for() -> None:
    cfg = _cfg()
    room = _room(_needed_gap_m(cfg) + 0.2)
    assert ground_truth_planner(room, cfg).plan((3.0, 0.7), (3.0, 3.3)).ok
    # Both sofas 0.2 m wider, as a map of that accuracy may show them: the passage closes.
    assert not ground_truth_planner(room, cfg, tolerance_m=0.2).plan((3.0, 0.7), (3.0, 3.3)).ok


def test_a_floor_lamp_blocks_with_its_pole_only() -> None:
    cfg = _cfg()
    room = _room(3.0, clutter=(_floor_lamp(3.0, 1.0),))
    keep_m = max(c.margin_m for c in cfg.classes) + cfg.planner.vehicle_radius_m

    def closest_to_base_m(path_xy_m: list[tuple[float, float]]) -> float:
        pts = densify(np.asarray(path_xy_m), 0.02)
        return float(np.hypot(np.maximum(np.abs(pts[:, 0] - 3.0) - 0.2, 0.0),
                              np.maximum(np.abs(pts[:, 1] - 1.0) - 0.2, 0.0)).min())

    # Its pole at the band is 3 cm wide: the true map lets the vehicle pass over its base.
    plain = ground_truth_planner(room, cfg).plan((2.0, 0.5), (3.8, 1.5))
    assert plain.ok and closest_to_base_m(plain.path_xy_m) < keep_m - 0.1


def test_clutter_below_the_band_stays_as_it_is() -> None:
    cfg = _cfg()
    rug = FurnitureObject(-2, "boxes", (3.0, 1.0), 0.0, (1.0, 1.0, 0.1),
                          (Box((3.0, 1.0, 0.05), (1.0, 1.0, 0.1)),), (100, 100, 100))
    room = _room(3.0, clutter=(rug,))
    assert ground_truth_planner(room, cfg).plan((3.0, 0.5), (3.0, 1.6)).ok
