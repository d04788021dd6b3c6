"""The demo crossing returns to where the vehicle stands, also when that is not PX4's home."""

from __future__ import annotations

import pytest

from companion.config import CompanionConfig
from companion.sim.demo_e2e import crossing_waypoints_room, feasible_seed
from companion.sim.sim_world import SimPlacement, start_point_room_m
from companion.sources.sim import room_from_config


def test_px4_rearm_probe_crossing_ends_at_the_vehicle_not_at_home() -> None:
    # After a landing away from home the room is placed around the vehicle: the map origin
    # (home) lies elsewhere in the room, and a crossing back to it could end in a wall.
    cfg = feasible_seed(CompanionConfig())
    room = room_from_config(cfg)
    sx, sy = start_point_room_m(room)
    vehicle_map_xy = (2.5, -1.5)
    placement = SimPlacement(room, (sx - vehicle_map_xy[0], sy - vehicle_map_xy[1]))
    wps = crossing_waypoints_room(placement, cfg)
    assert wps[-1] == (sx, sy)
    assert placement.room_to_map_xy(wps[-1]) == pytest.approx(vehicle_map_xy)
