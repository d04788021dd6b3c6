"""Judge a flown trajectory against a simulated room's true geometry (the safety figures).

The vehicle is a vertical cylinder of ``vehicle_radius_m`` and ``vehicle_height_m``. Two
collision judges: *exact* (the cylinder itself touches a primitive) and *with the vertical
margin* (the cylinder stretched by ``vertical_margin_m`` above and below, the band the planner
keeps free). The second is the safety figure: a path that grazes under a table top with less
than the margin to spare is a failure even if the airframe itself stays clear.
Clearances are horizontal distances from the vehicle's side (centre distance minus radius) to
the nearest primitive overlapping the judged vertical extent; negative means a collision.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.errors import SimulationError
from companion.sim.groundtruth import clearance_m, colliding_owners, densify
from companion.sim.world import Room

#: A trajectory is resampled this finely (metres) before it is judged.
JUDGE_STEP_M = 0.02


@dataclass(frozen=True)
class FlightVerdict:
    """How one flight went, judged against the true geometry (room frame, metres, seconds)."""

    #: The vehicle cylinder stretched by the vertical margin touched a primitive (walls included).
    collided: bool
    #: The vehicle cylinder itself touched a primitive.
    collided_exact: bool
    #: Judged points (every ``JUDGE_STEP_M``) that collide with the margin.
    collision_points: int
    #: Smallest side clearance to any primitive within the vertical extent incl. margin (< 0: collision).
    min_clearance_m: float
    #: ... to furniture only (walls excluded); ``inf`` when no furniture was ever at that height.
    min_object_clearance_m: float
    #: The goal was reached (horizontally within the acceptance radius, airborne).
    reached: bool
    #: Reached within the time limit.
    success: bool
    #: From the first sample to reaching the goal (or to the last sample when not reached).
    time_s: float
    #: Horizontal length flown up to reaching the goal (or in total when not reached).
    path_length_m: float
    #: Ids of the objects the vehicle collided with (with the margin); 0 is a wall.
    hit_object_ids: tuple[int, ...] = ()

    @property
    def safe_success(self) -> bool:
        """Reached in time without any collision (with the margin)."""
        return self.success and not self.collided


def side_clearance_m(room: Room, xyz_m: NDArray[np.floating], vehicle_radius_m: float,
                     extent_m: float, include_walls: bool = True) -> NDArray[np.float64]:
    """(N,) horizontal clearance from the side of a vehicle of ``vehicle_radius_m`` centred at
    each (N, 3) room-frame point to the nearest primitive overlapping ``z +- extent_m / 2``
    (``inf`` when none does); negative = overlap."""
    return clearance_m(room, xyz_m, extent_m, include_walls=include_walls) - vehicle_radius_m


def judge_flight(
    room: Room,
    xyz_m: NDArray[np.floating],
    stamps_s: NDArray[np.floating],
    goal_xy_m: tuple[float, float],
    *,
    vehicle_radius_m: float,
    vehicle_height_m: float,
    vertical_margin_m: float,
    acceptance_m: float,
    time_limit_s: float,
    min_airborne_m: float = 0.2,
) -> FlightVerdict:
    """Judge a flown trajectory: (N, 3) room-frame positions (metres, z up from the floor) at
    (N,) times (seconds, increasing).

    The goal counts as reached at the first sample within ``acceptance_m`` of ``goal_xy_m``
    horizontally and at least ``min_airborne_m`` above the floor; collisions and clearances are
    judged along the whole trajectory, resampled every :data:`JUDGE_STEP_M`.
    """
    p = np.asarray(xyz_m, dtype=np.float64).reshape(-1, 3)
    t = np.asarray(stamps_s, dtype=np.float64).reshape(-1)
    if len(p) == 0 or len(p) != len(t):
        raise SimulationError(f"judge_flight: need N >= 1 positions and as many stamps (got {len(p)}, {len(t)})")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(t))):
        raise SimulationError("judge_flight: positions and stamps must be finite")
    dense = densify(p, JUDGE_STEP_M) if len(p) >= 2 else p
    extent = vehicle_height_m + 2.0 * vertical_margin_m
    clear = side_clearance_m(room, dense, vehicle_radius_m, extent)
    clear_exact = side_clearance_m(room, dense, vehicle_radius_m, vehicle_height_m)
    clear_obj = side_clearance_m(room, dense, vehicle_radius_m, extent, include_walls=False)
    hits = clear < 0.0
    dist = np.hypot(p[:, 0] - goal_xy_m[0], p[:, 1] - goal_xy_m[1])
    at_goal = np.nonzero((dist <= acceptance_m) & (p[:, 2] >= min_airborne_m))[0]
    reached = len(at_goal) > 0
    k = int(at_goal[0]) if reached else len(p) - 1
    time_s = float(t[k] - t[0])
    length = float(np.sum(np.linalg.norm(np.diff(p[: k + 1, :2], axis=0), axis=1))) if k > 0 else 0.0
    return FlightVerdict(
        collided=bool(np.any(hits)),
        collided_exact=bool(np.any(clear_exact < 0.0)),
        collision_points=int(np.count_nonzero(hits)),
        min_clearance_m=float(np.min(clear)) if len(clear) else math.inf,
        min_object_clearance_m=float(np.min(clear_obj)) if len(clear_obj) else math.inf,
        reached=reached,
        success=reached and time_s <= time_limit_s,
        time_s=time_s,
        path_length_m=length,
        hit_object_ids=colliding_owners(room, dense[hits], vehicle_radius_m, extent) if np.any(hits) else (),
    )
