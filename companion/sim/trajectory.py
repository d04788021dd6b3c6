"""Scripted vehicle trajectories through a simulated room, for demos, tests and benchmarks.

A :class:`Trajectory` is a list of timed keyframes (position in the map frame, ENU yaw) with
linear interpolation in between, plus an optional sinusoidal yaw sweep (to look around, as a
mapping flight does). Builders route through a room on its ground truth so every pose keeps a
horizontal clearance from the primitives that overlap the vehicle's height band
(:func:`companion.sim.groundtruth.clearance_m`):

* :func:`doorway_transit`: from the first doorway to the second;
* :func:`lawnmower`: back-and-forth lanes across the room;
* :func:`perimeter_loop`: one lap along the walls.

The vehicle flies straight legs at constant speed and turns on the spot at corners, at a yaw
rate that, with the sweep added, never exceeds ``yaw_rate_max_rad_s``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from companion.errors import SimulationError
from companion.sim.groundtruth import (
    clearance_m,
    densify,
    interior_mask,
    occupancy_at_band,
    room_grid_spec,
)
from companion.sim.world import FurnitureObject, Room
from semmap.costmap import VerticalBand
from semmap.frames import Transform, pose_from_xyz_rpy, wrap_angle_rad
from semmap.grid import GridSpec, rasterize_polygon

log = logging.getLogger(__name__)

#: The default vehicle (a small indoor quadrotor) and clearance kept from furniture and walls.
VEHICLE_HEIGHT_M = 0.15
DEFAULT_CLEARANCE_M = 0.5


@dataclass(frozen=True)
class Keyframe:
    """The vehicle at time ``t_s``: position (map frame, metres) and ENU yaw (radians)."""

    t_s: float
    x_m: float
    y_m: float
    z_m: float
    yaw_rad: float


class Trajectory:
    """Timed keyframes, linearly interpolated (yaw unwrapped), plus an optional yaw sweep
    ``yaw_sweep_rad * sin(2 pi t / sweep_period_s)`` added on top."""

    def __init__(
        self, keyframes: Sequence[Keyframe], yaw_sweep_rad: float = 0.0, sweep_period_s: float = 6.0,
    ) -> None:
        if len(keyframes) < 1:
            raise SimulationError("a trajectory needs at least one keyframe")
        t = np.array([k.t_s for k in keyframes], dtype=np.float64)
        if np.any(np.diff(t) < 0):
            raise SimulationError("trajectory keyframes must be in time order")
        self.keyframes = tuple(keyframes)
        self._t = t
        self._xyz = np.array([[k.x_m, k.y_m, k.z_m] for k in keyframes], dtype=np.float64)
        self._yaw = np.unwrap(np.array([k.yaw_rad for k in keyframes], dtype=np.float64))
        self.yaw_sweep_rad = float(yaw_sweep_rad)
        self.sweep_period_s = float(sweep_period_s)

    @property
    def duration_s(self) -> float:
        """Seconds from the first keyframe to the last."""
        return float(self._t[-1] - self._t[0])

    @property
    def start_s(self) -> float:
        """Time of the first keyframe, seconds."""
        return float(self._t[0])

    def state_at(self, t_s: float) -> tuple[NDArray[np.float64], float]:
        """(xyz_map_m (3,), yaw_rad) at time ``t_s`` (clamped to the trajectory's span)."""
        t = float(np.clip(t_s, self._t[0], self._t[-1]))
        xyz = np.array([np.interp(t, self._t, self._xyz[:, i]) for i in range(3)])
        yaw = float(np.interp(t, self._t, self._yaw))
        if self.yaw_sweep_rad:
            yaw += self.yaw_sweep_rad * math.sin(2.0 * math.pi * (t - self._t[0]) / self.sweep_period_s)
        return xyz, wrap_angle_rad(yaw)

    def T_map_body(self, t_s: float) -> Transform:  # noqa: N802 - frame names
        """(4, 4) level body pose (FLU, no roll or pitch) at ``t_s``."""
        xyz, yaw = self.state_at(t_s)
        return pose_from_xyz_rpy(float(xyz[0]), float(xyz[1]), float(xyz[2]), 0.0, 0.0, yaw)

    def samples(self, rate_hz: float) -> list[tuple[float, Transform]]:
        """(stamp_s, T_map_body) every ``1 / rate_hz`` from start to end inclusive."""
        n = int(math.floor(self.duration_s * rate_hz + 1e-9)) + 1
        return [(self.start_s + i / rate_hz, self.T_map_body(self.start_s + i / rate_hz)) for i in range(n)]

    def positions_m(self, rate_hz: float) -> NDArray[np.float64]:
        """(N, 3) positions sampled at ``rate_hz``."""
        n = int(math.floor(self.duration_s * rate_hz + 1e-9)) + 1
        return np.array([self.state_at(self.start_s + i / rate_hz)[0] for i in range(n)])

    def pose_provider(self, rate_hz: float) -> Callable[[], tuple[float, Transform] | None]:
        """A :class:`~companion.sources.sim.SimFrameSource` pose provider stepping through the
        trajectory at ``rate_hz`` (simulated time) and returning None after the end."""
        samples = iter(self.samples(rate_hz))
        return lambda: next(samples, None)


# --- routing on the ground truth --------------------------------------------------------

def blocking_objects(
    room: Room, altitude_m: float, vehicle_height_m: float, vertical_margin_m: float,
) -> list[FurnitureObject]:
    """Objects whose height range meets the band ``altitude +- (height / 2 + margin)``: a
    semantic map keeps the vehicle out of their whole footprint (no flying under tables)."""
    band = VerticalBand.for_altitude(altitude_m, vehicle_height_m, vertical_margin_m)
    return [o for o in room.objects if band.intersects(*o.z_range_m)]


def clearance_grid(
    room: Room, altitude_m: float, vehicle_height_m: float = VEHICLE_HEIGHT_M,
    resolution_m: float = 0.05, vertical_margin_m: float | None = 0.1,
) -> tuple[GridSpec, NDArray[np.float64]]:
    """(spec, (rows, cols) metres): distance from each cell centre to the nearest primitive
    overlapping the vehicle's height band at ``altitude_m`` and, unless ``vertical_margin_m``
    is None, to the whole footprint of every object in :func:`blocking_objects`; 0 outside
    the room."""
    spec = room_grid_spec(room, resolution_m)
    band = VerticalBand.for_altitude(altitude_m, vehicle_height_m, 0.0)
    occ = occupancy_at_band(room, spec, band)
    if vertical_margin_m is not None:
        for obj in blocking_objects(room, altitude_m, vehicle_height_m, vertical_margin_m):
            occ |= rasterize_polygon(spec, obj.footprint_xy_m())
    dist = ndimage.distance_transform_edt(~occ) * resolution_m
    dist[~interior_mask(room, spec)] = 0.0
    return spec, dist


def _grid_path(free: NDArray[np.bool_], start: tuple[int, int], goal: tuple[int, int]) -> list[tuple[int, int]]:
    """Shortest 8-connected path over ``free`` cells (Dijkstra); [] when unreachable."""
    rows, cols = free.shape
    idx = np.full(free.shape, -1, dtype=np.int64)
    cells = np.argwhere(free)  # (n, 2) row, col
    idx[free] = np.arange(len(cells))
    src, dst, w = [], [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        nr, nc = cells[:, 0] + dr, cells[:, 1] + dc
        ok = (nr >= 0) & (nr < rows) & (nc >= 0) & (nc < cols)
        ok[ok] &= free[nr[ok], nc[ok]]
        src.append(idx[cells[ok, 0], cells[ok, 1]])
        dst.append(idx[nr[ok], nc[ok]])
        w.append(np.full(int(ok.sum()), math.hypot(dr, dc)))
    n = int(free.sum())
    g = coo_matrix((np.concatenate(w), (np.concatenate(src), np.concatenate(dst))), shape=(n, n)).tocsr()
    s, t = idx[start], idx[goal]
    if s < 0 or t < 0:
        return []
    _, pred = dijkstra(g, directed=False, indices=int(s), return_predecessors=True)
    if pred[t] < 0 and s != t:
        return []
    path = [int(t)]
    while path[-1] != s:
        path.append(int(pred[path[-1]]))
    return [tuple(int(v) for v in cells[i]) for i in reversed(path)]  # type: ignore[misc]


def _segment_clear(spec: GridSpec, dist: NDArray[np.float64], a: NDArray[np.float64],
                   b: NDArray[np.float64], need_m: float) -> bool:
    pts = densify(np.array([a, b]), spec.resolution_m / 2)
    rc = spec.cell_of(pts)
    if not np.all(spec.contains_rc(rc)):
        return False
    return bool(np.all(dist[rc[:, 0], rc[:, 1]] >= need_m))


def plan_route(
    room: Room, waypoints_xy_m: Sequence[tuple[float, float]], altitude_m: float,
    clearance_required_m: float = DEFAULT_CLEARANCE_M, vehicle_height_m: float = VEHICLE_HEIGHT_M,
    resolution_m: float = 0.05, vertical_margin_m: float | None = 0.1,
    largest_component_only: bool = False,
) -> NDArray[np.float64]:
    """(K, 2) polyline visiting the waypoints in order, every point at least
    ``clearance_required_m`` (horizontally) from primitives in the vehicle's band and from
    the footprints of blocking objects (see :func:`clearance_grid`).

    Waypoints that are not clear are moved to the nearest clear cell; legs are grid shortest
    paths shortened by line of sight. Raises :class:`SimulationError` if a leg has no route.
    ``largest_component_only`` restricts the route to the largest connected clear region (for
    coverage flights: waypoints in pockets furniture closes off move to its edge instead).
    """
    spec, dist = clearance_grid(room, altitude_m, vehicle_height_m, resolution_m, vertical_margin_m)
    # Cell centres can be half a diagonal closer to an obstacle than the grid distance says.
    need = clearance_required_m + resolution_m * 0.75
    free = dist >= need
    if not np.any(free):
        raise SimulationError(f"no place in the room keeps {clearance_required_m:.2f} m clearance")
    if largest_component_only:
        labels, n = ndimage.label(free, structure=np.ones((3, 3), dtype=bool))
        if n > 1:
            sizes = np.bincount(labels.ravel())[1:]
            free = labels == (1 + int(np.argmax(sizes)))
    free_cells = np.argwhere(free)

    def snap(xy: tuple[float, float]) -> tuple[int, int]:
        rc = spec.cell_of(np.array([xy]))[0]
        if spec.contains_rc(rc[None])[0] and free[rc[0], rc[1]]:
            return int(rc[0]), int(rc[1])
        k = int(np.argmin(np.sum((free_cells - rc) ** 2, axis=1)))
        return int(free_cells[k, 0]), int(free_cells[k, 1])

    cells = [snap(w) for w in waypoints_xy_m]
    route: list[NDArray[np.float64]] = []
    for a, b in zip(cells[:-1], cells[1:], strict=True):
        leg = _grid_path(free, a, b)
        if not leg:
            xa, xb = spec.center_of(np.array([a, b]))
            raise SimulationError(
                f"no route with {clearance_required_m:.2f} m clearance from ({xa[0]:.2f}, {xa[1]:.2f}) "
                f"to ({xb[0]:.2f}, {xb[1]:.2f}) at {altitude_m:.2f} m"
            )
        pts = spec.center_of(np.array(leg))
        # Line-of-sight shortcuts: from each kept point jump to the farthest visible one.
        kept = [pts[0]]
        i = 0
        while i < len(pts) - 1:
            j = len(pts) - 1
            while j > i + 1 and not _segment_clear(spec, dist, pts[i], pts[j], need):
                j -= 1
            kept.append(pts[j])
            i = j
        route.extend(kept if not route else kept[1:])
    if len(route) == 1:
        route.append(route[0].copy())
    out = np.array(route)
    # Drop zero-length steps (consecutive waypoints in the same cell).
    keep = np.concatenate([[True], np.linalg.norm(np.diff(out, axis=0), axis=1) > 1e-9])
    return out[keep] if keep.sum() >= 2 else out[:2]


def fly_route(
    route_xy_m: NDArray[np.floating], altitude_m: float, speed_m_s: float = 0.5,
    yaw_rate_max_rad_s: float = math.radians(60.0), yaw_sweep_rad: float = 0.0,
    sweep_period_s: float = 6.0, start_yaw_rad: float | None = None,
) -> Trajectory:
    """Fly a (K, 2) polyline at ``altitude_m``: straight legs at ``speed_m_s`` heading along
    the leg, turns on the spot at corners. The turn rate leaves room for the sweep so the
    total yaw rate stays within ``yaw_rate_max_rad_s``."""
    pts = np.asarray(route_xy_m, dtype=np.float64).reshape(-1, 2)
    sweep_rate = abs(yaw_sweep_rad) * 2.0 * math.pi / sweep_period_s
    turn_rate = yaw_rate_max_rad_s - sweep_rate
    if speed_m_s <= 0 or turn_rate <= 1e-3:
        raise SimulationError(
            f"speed must be > 0 and the sweep ({math.degrees(sweep_rate):.0f} deg/s) must leave yaw "
            f"rate for turns (max {math.degrees(yaw_rate_max_rad_s):.0f} deg/s)"
        )
    legs = np.diff(pts, axis=0)
    lengths = np.linalg.norm(legs, axis=1)
    headings = [math.atan2(d[1], d[0]) for d, n in zip(legs, lengths, strict=True) if n > 1e-9]
    yaw = start_yaw_rad if start_yaw_rad is not None else (headings[0] if headings else 0.0)
    t = 0.0
    kfs = [Keyframe(t, pts[0, 0], pts[0, 1], altitude_m, yaw)]
    for p0, p1, n in zip(pts[:-1], pts[1:], lengths, strict=True):
        if n <= 1e-9:
            continue
        heading = yaw + wrap_angle_rad(math.atan2(p1[1] - p0[1], p1[0] - p0[0]) - yaw)
        if abs(heading - yaw) > 1e-6:
            t += abs(heading - yaw) / turn_rate
            kfs.append(Keyframe(t, p0[0], p0[1], altitude_m, heading))
            yaw = heading
        t += n / speed_m_s
        kfs.append(Keyframe(t, p1[0], p1[1], altitude_m, yaw))
    return Trajectory(kfs, yaw_sweep_rad=yaw_sweep_rad, sweep_period_s=sweep_period_s)


def check_clearance(
    room: Room, traj: Trajectory, clearance_required_m: float,
    vehicle_height_m: float = VEHICLE_HEIGHT_M, vertical_margin_m: float | None = 0.1,
    step_m: float = 0.02,
) -> float:
    """Smallest exact horizontal clearance along the trajectory (metres) from primitives in
    the vehicle's band and (unless ``vertical_margin_m`` is None) from the footprints of
    blocking objects; raises :class:`SimulationError` if below ``clearance_required_m``."""
    path = densify(traj.positions_m(20.0), step_m)
    c = clearance_m(room, path, vehicle_height_m)
    if vertical_margin_m is not None and len(path):
        z = float(np.median(path[:, 2]))
        for obj in blocking_objects(room, z, vehicle_height_m, vertical_margin_m):
            c = np.minimum(c, obj.footprint_distance_m(path[:, :2]))
    worst = float(np.min(c)) if len(c) else math.inf
    if worst < clearance_required_m - 1e-6:
        k = int(np.argmin(c))
        raise SimulationError(
            f"trajectory passes {worst:.3f} m from an obstacle at ({path[k, 0]:.2f}, {path[k, 1]:.2f}) "
            f"(required {clearance_required_m:.2f} m)"
        )
    return worst


# --- builders ---------------------------------------------------------------------------

def _fly_waypoints(
    room: Room, waypoints_xy_m: Sequence[tuple[float, float]], altitude_m: float, speed_m_s: float,
    yaw_rate_max_rad_s: float, yaw_sweep_rad: float, sweep_period_s: float,
    clearance_required_m: float, min_clearance_m: float | None, vehicle_height_m: float,
    vertical_margin_m: float | None, largest_component_only: bool = False,
) -> Trajectory:
    """Route and fly; if no route keeps ``clearance_required_m``, retry with 5 cm less down
    to ``min_clearance_m`` (None: no retry). The trajectory's clearance is checked exactly."""
    clearance = clearance_required_m
    floor_m = clearance_required_m if min_clearance_m is None else min(min_clearance_m, clearance_required_m)
    while True:
        try:
            route = plan_route(room, waypoints_xy_m, altitude_m, clearance, vehicle_height_m,
                               vertical_margin_m=vertical_margin_m,
                               largest_component_only=largest_component_only)
            break
        except SimulationError:
            if clearance - 0.05 < floor_m - 1e-9:
                raise
            clearance -= 0.05
    if clearance < clearance_required_m:
        log.warning("no route keeps %.2f m clearance at %.2f m; flying with %.2f m",
                    clearance_required_m, altitude_m, clearance)
    traj = fly_route(route, altitude_m, speed_m_s, yaw_rate_max_rad_s, yaw_sweep_rad, sweep_period_s)
    check_clearance(room, traj, clearance, vehicle_height_m, vertical_margin_m)
    return traj


def doorway_transit(
    room: Room, altitude_m: float, speed_m_s: float = 0.5,
    yaw_rate_max_rad_s: float = math.radians(60.0), yaw_sweep_rad: float = math.radians(35.0),
    sweep_period_s: float = 6.0, clearance_required_m: float = DEFAULT_CLEARANCE_M,
    min_clearance_m: float | None = 0.3, vehicle_height_m: float = VEHICLE_HEIGHT_M,
    vertical_margin_m: float | None = 0.1,
) -> Trajectory:
    """From just inside the first doorway to just inside the second (or across the room
    when there is one doorway), sweeping the yaw to look around. Builders keep
    ``clearance_required_m`` where a route allows it, else as much as possible down to
    ``min_clearance_m`` (None: exactly the required one or :class:`SimulationError`), and
    avoid whole footprints of objects within ``vertical_margin_m`` of the vehicle's band
    (None: only the primitives in the band, i.e. flying under tables is allowed)."""
    if not room.doorways:
        raise SimulationError("the room has no doorway to start from")
    start = room.doorways[0].inside_point_m(0.6)
    if len(room.doorways) >= 2:
        goal = room.doorways[1].inside_point_m(0.6)
    else:
        goal = (room.width_m - start[0], room.depth_m - start[1])
    return _fly_waypoints(room, [start, goal], altitude_m, speed_m_s, yaw_rate_max_rad_s, yaw_sweep_rad,
                          sweep_period_s, clearance_required_m, min_clearance_m, vehicle_height_m,
                          vertical_margin_m)


def lawnmower(
    room: Room, altitude_m: float, lane_spacing_m: float = 1.0, speed_m_s: float = 0.5,
    yaw_rate_max_rad_s: float = math.radians(60.0), yaw_sweep_rad: float = 0.0,
    sweep_period_s: float = 6.0, clearance_required_m: float = DEFAULT_CLEARANCE_M,
    min_clearance_m: float | None = 0.3, vehicle_height_m: float = VEHICLE_HEIGHT_M,
    vertical_margin_m: float | None = 0.1,
) -> Trajectory:
    """Back-and-forth lanes along the room's longer side, ``lane_spacing_m`` apart, routed
    around furniture in the vehicle's band (within the largest region the vehicle can reach:
    corners closed off by furniture are skipped)."""
    inset = clearance_required_m + 0.1
    along_x = room.width_m >= room.depth_m
    span = room.depth_m if along_x else room.width_m
    length = room.width_m if along_x else room.depth_m
    n_lanes = max(1, int(math.floor((span - 2 * inset) / lane_spacing_m)) + 1)
    offsets = np.linspace(inset, span - inset, n_lanes) if n_lanes > 1 else np.array([span / 2])
    wps: list[tuple[float, float]] = []
    for i, o in enumerate(offsets):
        a, b = (inset, length - inset) if i % 2 == 0 else (length - inset, inset)
        for s in (a, b):
            wps.append((s, float(o)) if along_x else (float(o), s))
    return _fly_waypoints(room, wps, altitude_m, speed_m_s, yaw_rate_max_rad_s, yaw_sweep_rad,
                          sweep_period_s, clearance_required_m, min_clearance_m, vehicle_height_m,
                          vertical_margin_m, largest_component_only=True)


def perimeter_loop(
    room: Room, altitude_m: float, inset_m: float = 0.9, speed_m_s: float = 0.5,
    yaw_rate_max_rad_s: float = math.radians(60.0), yaw_sweep_rad: float = 0.0,
    sweep_period_s: float = 6.0, clearance_required_m: float = DEFAULT_CLEARANCE_M,
    min_clearance_m: float | None = 0.3, vehicle_height_m: float = VEHICLE_HEIGHT_M,
    vertical_margin_m: float | None = 0.1,
) -> Trajectory:
    """One counter-clockwise lap ``inset_m`` inside the walls, back to the start (within the
    largest region the vehicle can reach)."""
    w, d = room.width_m, room.depth_m
    corners = [(inset_m, inset_m), (w - inset_m, inset_m), (w - inset_m, d - inset_m),
               (inset_m, d - inset_m), (inset_m, inset_m)]
    return _fly_waypoints(room, corners, altitude_m, speed_m_s, yaw_rate_max_rad_s, yaw_sweep_rad,
                          sweep_period_s, clearance_required_m, min_clearance_m, vehicle_height_m,
                          vertical_margin_m, largest_component_only=True)
