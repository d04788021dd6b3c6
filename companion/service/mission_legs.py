"""Mission legs and what the mission runner reads from the vehicle's state.

A downloaded mission becomes :class:`Leg` s (map-frame goals at the flight altitude); each is
flown to :func:`arrived`, and reported in a :class:`LegReport`. Positions are in the map frame
(ENU, z above the floor the vehicle took off from: :class:`~companion.mavlink.state.MapFrame`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from pymavlink.dialects.v20 import common as mavlink

from companion.errors import MissionError
from companion.mavlink.mission_download import waypoint_ned_m
from companion.mavlink.state import HomePosition, MapFrame, VehicleState
from companion.missions import MissionItemInt
from semmap.frames import ned_to_enu

log = logging.getLogger(__name__)

#: Default distance at which a waypoint counts as reached (metres).
DEFAULT_ACCEPTANCE_M = 0.3
#: How often the setpoint slot is refreshed from the trajectory.
FEED_PERIOD_S = 0.05
#: A waypoint is reached only by a vehicle this slow (m/s, horizontal): PX4 trails its
#: setpoints by about half a second, so it can be within the acceptance radius still moving
#: at cruise speed, and a leg planned from rest (or PX4's Land) would carry it on.
SETTLED_SPEED_M_S = 0.2


@dataclass(frozen=True)
class Leg:
    """One mission leg: fly to ``goal_xy_m`` (map frame ENU) at ``altitude_m``."""

    seq: int
    goal_xy_m: tuple[float, float]
    altitude_m: float
    acceptance_m: float = DEFAULT_ACCEPTANCE_M


def mission_legs(items: Sequence[MissionItemInt], home: HomePosition, altitude_m: float) -> list[Leg]:
    """The waypoint items of a downloaded mission as legs at ``altitude_m`` (the planner's
    flight altitude: the semantic map's band is built for it). Takeoff, land and RTL items
    are flown by the service itself; other items are skipped with a log line."""
    legs = []
    for it in items:
        if it.command != mavlink.MAV_CMD_NAV_WAYPOINT:
            if it.command not in (mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_CMD_NAV_LAND,
                                  mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH):
                log.info("mission item %d (%s) is not flown by the companion", it.seq, it.command_name)
            continue
        n, e, d = waypoint_ned_m(it, home)
        x, y, _z = ned_to_enu(n, e, d)
        acc = it.param2 if it.param2 > 0 else DEFAULT_ACCEPTANCE_M
        legs.append(Leg(it.seq, (x, y), altitude_m, acc))
    if not legs:
        raise MissionError("the autopilot's mission has no waypoint to fly")
    return legs


def position_enu(state: VehicleState) -> NDArray[np.float64] | None:
    """(3,) the vehicle's map-frame position (z above home), or None before the position
    and the home position are known."""
    pos = state.position_map_m
    return None if pos is None else np.array(pos)


def map_frame_of(state: VehicleState) -> MapFrame:
    """The map frame of ``state``; a :class:`MissionError` before PX4 reports home (no
    setpoint height can be known then)."""
    frame = state.map_frame
    if frame is None:
        raise MissionError("no home position from the autopilot: heights above home are unknown")
    return frame


def horizontal_speed_m_s(state: VehicleState) -> float | None:
    """The vehicle's horizontal speed (m/s), or None before PX4 reports a velocity."""
    vel = state.velocity_ned_m_s
    return None if vel is None else math.hypot(vel[0], vel[1])


def arrived(state: VehicleState, goal_xy_m: NDArray[np.floating], acceptance_m: float) -> bool:
    """The vehicle is within ``acceptance_m`` of ``goal_xy_m`` (map frame) and has come to
    rest there (:data:`SETTLED_SPEED_M_S`)."""
    pos = position_enu(state)
    speed = horizontal_speed_m_s(state)
    return (pos is not None and speed is not None and speed <= SETTLED_SPEED_M_S
            and float(np.linalg.norm(pos[:2] - goal_xy_m)) <= acceptance_m)



@dataclass
class LegReport:
    """How one leg went."""

    seq: int
    goal_xy_m: tuple[float, float]
    reached: bool = False
    plans: int = 0
    replans_invalid: int = 0
    failed_plans: int = 0
    plan_ms: list[float] = field(default_factory=list)
    duration_s: float = 0.0
    final_error_m: float = math.nan
    snapped_goal: bool = False  # the leg ended at the nearest free point to a blocked waypoint
    tracking_faults: int = 0  # holds because the vehicle did not follow its setpoints

