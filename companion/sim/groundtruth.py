"""Ground truth of a simulated room: occupancy at a height band, costmaps, collision judge.

The judge for every accuracy and safety figure. Collision and clearance are computed exactly
against the primitives (oriented boxes), not against a rasterised grid.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from companion.config import CompanionConfig
from companion.sim.world import Box, Room
from planner.planner import Planner
from semmap.costmap import (
    FREE_SPACE,
    LETHAL_OBSTACLE,
    NO_INFORMATION,
    Costmap,
    ObjectFootprint,
    VerticalBand,
)
from semmap.grid import GridSpec, rasterize_polygon
from semmap.layers import paint_objects


def room_grid_spec(room: Room, resolution_m: float = 0.05, pad_m: float = 0.5) -> GridSpec:
    """A grid covering the room and its walls with ``pad_m`` to spare."""
    return GridSpec.covering(-pad_m, -pad_m, room.width_m + pad_m, room.depth_m + pad_m, resolution_m)


def boxes_in_band(room: Room, band: VerticalBand) -> list[tuple[Box, int]]:
    """Primitives (with owner id, 0 = wall) whose height range intersects the band."""
    return [(b, oid) for b, oid in room.all_boxes() if band.intersects(*b.z_range_m)]


def occupancy_at_band(room: Room, spec: GridSpec, band: VerticalBand) -> NDArray[np.bool_]:
    """(rows, cols) True where any primitive occupies some height inside the band.

    With a thin band at flight altitude this is what a depth slice / 2D lidar map sees: the
    legs of a table, not its top.
    """
    occ = np.zeros(spec.shape_rc, dtype=bool)
    for box, _ in boxes_in_band(room, band):
        occ |= rasterize_polygon(spec, box.corners_xy_m())
    return occ


def interior_mask(room: Room, spec: GridSpec) -> NDArray[np.bool_]:
    """Cells inside the room's walls (the space a vehicle could observe)."""
    X, Y = spec.cell_centers_xy()
    return (X >= 0) & (X <= room.width_m) & (Y >= 0) & (Y <= room.depth_m)


def object_footprints(
    room: Room, margins_m: Mapping[str, float] | None = None
) -> list[ObjectFootprint]:
    """Ground-truth :class:`ObjectFootprint` of every object (existence 1)."""
    margins = margins_m or {}
    out = []
    for o in room.objects:
        z0, z1 = o.z_range_m
        out.append(
            ObjectFootprint(
                object_id=o.object_id, class_name=o.class_name, polygon_xy_m=o.footprint_xy_m(),
                z_min_m=z0, z_max_m=z1, existence=1.0, margin_m=float(margins.get(o.class_name, 0.0)),
            )
        )
    return out


def semantic_costmap(
    room: Room, spec: GridSpec, band: VerticalBand, class_names: list[str] | None = None,
    margins_m: Mapping[str, float] | None = None,
) -> Costmap:
    """The ideal semantic costmap at a band: walls and slice hits are lethal, the interior is
    free, outside the walls is unknown; the objects are costed by the map's own layers (the
    whole footprint of every object that blocks the band is lethal, with its class margin
    from ``margins_m`` around it)."""
    cost = np.full(spec.shape_rc, NO_INFORMATION, dtype=np.uint8)
    cost[interior_mask(room, spec)] = FREE_SPACE
    cost[occupancy_at_band(room, spec, band)] = LETHAL_OBSTACLE
    class_index = np.full(spec.shape_rc, -1, dtype=np.int16)
    fps = object_footprints(room, margins_m)
    for fp in fps:
        if fp.blocks(band) and class_names and fp.class_name in class_names:
            class_index[fp.mask(spec)] = class_names.index(fp.class_name)
    return paint_objects(Costmap(spec, cost, band, class_index=class_index), fps, band)


def ground_truth_planner(room: Room, cfg: CompanionConfig, *, altitude_m: float | None = None,
                         tolerance_m: float = 0.0,
                         time_limit_s: float | None = None) -> Planner:
    """The configured planner on the room's ideal semantic costmap (room frame, the room as
    geofence, objects with their class margins): what a perfect map would allow.

    ``tolerance_m``: every object's margin grows by it and the band by it above and below, as a
    map of that accuracy could show them. Clutter (a floor lamp, a shelf) blocks with its
    slice at the band only: it is none of our classes.
    """
    p = cfg.planner
    altitude = p.flight_altitude_m if altitude_m is None else float(altitude_m)
    margins = {c.name: c.margin_m + tolerance_m for c in cfg.classes}
    band = p.band_at(altitude)
    band = VerticalBand(band.z_min_m - tolerance_m, band.z_max_m + tolerance_m)
    spec = room_grid_spec(room, cfg.map.resolution_m)
    cm = semantic_costmap(room, spec, band, [c.name for c in cfg.classes], margins)
    update: dict[str, object] = {"flight_altitude_m": altitude, "refine_with_ompl": False,
                                 "geofence_xy_m": (0.0, 0.0, room.width_m, room.depth_m)}
    if time_limit_s is not None:
        update["time_limit_s"] = float(time_limit_s)
    planner = Planner(p.model_copy(update=update))
    planner.set_map(cm)
    return planner


def metric_costmap(room: Room, spec: GridSpec, altitude_m: float, slice_half_m: float = 0.05) -> Costmap:
    """What a plain 2D map gives: a thin depth slice at flight altitude, no objects."""
    band = VerticalBand(altitude_m - slice_half_m, altitude_m + slice_half_m)
    cost = np.full(spec.shape_rc, NO_INFORMATION, dtype=np.uint8)
    cost[interior_mask(room, spec)] = FREE_SPACE
    cost[occupancy_at_band(room, spec, band)] = LETHAL_OBSTACLE
    return Costmap(spec, cost, band)


def _box_distance_xy(box: Box, xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """Horizontal distance from (N, 2) points to an oriented box's footprint (0 inside)."""
    c, s = np.cos(box.yaw_rad), np.sin(box.yaw_rad)
    d = xy - np.array(box.center_m[:2])
    lx = c * d[:, 0] + s * d[:, 1]
    ly = -s * d[:, 0] + c * d[:, 1]
    ex = np.maximum(np.abs(lx) - box.size_m[0] / 2, 0.0)
    ey = np.maximum(np.abs(ly) - box.size_m[1] / 2, 0.0)
    return np.hypot(ex, ey)


def clearance_m(
    room: Room, xyz_m: NDArray[np.floating], vehicle_height_m: float, include_walls: bool = True,
) -> NDArray[np.float64]:
    """(N,) horizontal distance from each vehicle position (N, 3) to the nearest primitive that
    overlaps the vehicle's vertical extent (z +- height/2) there. ``inf`` when none does."""
    pts = np.asarray(xyz_m, dtype=np.float64).reshape(-1, 3)
    out = np.full(len(pts), np.inf)
    half = vehicle_height_m / 2.0
    for box, oid in room.all_boxes():
        if oid == 0 and not include_walls:
            continue
        z0, z1 = box.z_range_m
        overlap = (pts[:, 2] - half <= z1) & (pts[:, 2] + half >= z0)
        if not np.any(overlap):
            continue
        d = _box_distance_xy(box, pts[overlap, :2])
        out[overlap] = np.minimum(out[overlap], d)
    return out


def collides(
    room: Room, xyz_m: NDArray[np.floating], vehicle_radius_m: float, vehicle_height_m: float,
) -> NDArray[np.bool_]:
    """(N,) True where a vertical cylinder (radius, height) centred at the point touches any
    primitive, walls included. The judge for every collision figure."""
    return clearance_m(room, xyz_m, vehicle_height_m) < vehicle_radius_m


def colliding_owners(
    room: Room, xyz_m: NDArray[np.floating], vehicle_radius_m: float, vehicle_height_m: float,
) -> tuple[int, ...]:
    """Sorted owners (object id, 0 = a wall) of the primitives that a vertical cylinder (radius,
    height) centred at any of the (N, 3) points touches (the same rule as :func:`collides`)."""
    pts = np.asarray(xyz_m, dtype=np.float64).reshape(-1, 3)
    half = vehicle_height_m / 2.0
    owners: set[int] = set()
    for box, oid in room.all_boxes():
        if oid in owners:
            continue
        z0, z1 = box.z_range_m
        overlap = (pts[:, 2] - half <= z1) & (pts[:, 2] + half >= z0)
        if np.any(overlap) and np.any(_box_distance_xy(box, pts[overlap, :2]) < vehicle_radius_m):
            owners.add(oid)
    return tuple(sorted(owners))


def path_collides(
    room: Room, path_xyz_m: NDArray[np.floating], vehicle_radius_m: float,
    vehicle_height_m: float, step_m: float = 0.02,
) -> bool:
    """True if the polyline (K, 3), densely resampled every ``step_m``, ever collides."""
    return bool(np.any(collides(room, densify(path_xyz_m, step_m), vehicle_radius_m, vehicle_height_m)))


def densify(path_m: NDArray[np.floating], step_m: float) -> NDArray[np.float64]:
    """Resample a polyline (K, D) so consecutive points are at most ``step_m`` apart."""
    p = np.asarray(path_m, dtype=np.float64)
    if len(p) < 2:
        return p.copy()
    out = [p[:1]]
    for a, b in zip(p[:-1], p[1:], strict=True):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step_m)))
        t = np.linspace(0.0, 1.0, n + 1)[1:, None]
        out.append(a + t * (b - a))
    return np.concatenate(out)


def free_path_exists(room: Room, vehicle_radius_m: float, resolution_m: float = 0.1) -> bool:
    """True if every doorway connects to the first through free space at all heights (the
    full-height occupancy inflated by the vehicle radius)."""
    spec = room_grid_spec(room, resolution_m)
    occ = occupancy_at_band(room, spec, VerticalBand(0.0, room.wall_height_m))
    free = ~ndimage.binary_dilation(occ, iterations=max(1, int(np.ceil(vehicle_radius_m / resolution_m))))
    free &= interior_mask(room, spec)
    if len(room.doorways) < 2:
        return True
    starts = spec.cell_of(np.array([d.inside_point_m(0.6) for d in room.doorways]))
    if not all(spec.contains_rc(s[None])[0] and free[s[0], s[1]] for s in starts):
        return False
    seen = np.zeros_like(free)
    q = deque([tuple(starts[0])])
    seen[tuple(starts[0])] = True
    while q:
        r, c = q.popleft()
        for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            rr, cc = r + dr, c + dc
            if 0 <= rr < spec.rows and 0 <= cc < spec.cols and free[rr, cc] and not seen[rr, cc]:
                seen[rr, cc] = True
                q.append((rr, cc))
    return all(seen[s[0], s[1]] for s in starts[1:])
