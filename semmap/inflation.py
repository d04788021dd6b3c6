"""The inflation layer: the final cost of every cell for a vehicle at the flight altitude.

The costmap's layers (:mod:`semmap.layers`) paint what the map knows at the altitude: walls
and clutter as lethal, each object's footprint as lethal with its class margin as inscribed,
and the margins' decay as soft cost. This layer, like nav2's ``InflationLayer``, adds the
vehicle: which cells the vehicle's centre may not touch (``blocked``), how far each cell is
from them (``clearance_m``), where the vehicle's whole radius fits (``free``) and the 0..1
cost of flying through each cell, whose proximity term decays with the costmap's
``clearance_decay_m`` (:func:`semmap.layers.cost_decay`), the one decay of the map.

Clearance is conservative: ``clearance_m`` of a cell is a lower bound on the horizontal
distance from *any* point of the cell to the nearest blocked cell's square (centre distance
minus one cell diagonal; from a blocked cell outside a class margin, less the tracking
margin too), and a point is free when that bound is at least the vehicle radius plus a quarter
cell (the largest gap between motion samples spaced half a cell apart).

:func:`reinflate` recomputes the layer only in the window a map change can influence, so a
new object does not cost a whole-map distance transform.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from semmap.costmap import (
    DEFAULT_CLEARANCE_DECAY_M,
    INSCRIBED_INFLATED_OBSTACLE,
    LETHAL_OBSTACLE,
    MAX_NON_OBSTACLE,
    NO_INFORMATION,
    Costmap,
    VerticalBand,
)
from semmap.errors import ConfigError
from semmap.grid import Bounds, GridSpec
from semmap.layers import cost_decay


@dataclass(frozen=True)
class InflationParams:
    """The vehicle the layer inflates for.

    ``vehicle_radius_m``: horizontal radius of the vehicle (nav2's inscribed radius).
    ``tracking_margin_m``: kept beyond the radius from every blocked cell outside an object's
    class margin (walls, unclassified clutter, the geofence), because the autopilot flies a
    few centimetres off the commanded path; a class margin already keeps the vehicle that far
    from its object when it is at least this wide. ``unknown_cost`` (0..1): cost of an
    unknown cell relative to the highest traversable cost; 1 forbids unknown space.
    ``geofence_xy_m``: the vehicle (its whole radius) stays inside it.
    """

    vehicle_radius_m: float
    tracking_margin_m: float = 0.0
    unknown_cost: float = 0.5
    #: [x_min, y_min, x_max, y_max] in the map frame; cells outside it are blocked.
    geofence_xy_m: tuple[float, float, float, float] | None = None

    def __post_init__(self) -> None:
        if not self.vehicle_radius_m > 0.0:
            raise ConfigError(f"inflation: vehicle_radius_m must be > 0 (got {self.vehicle_radius_m})")
        if not self.tracking_margin_m >= 0.0:
            raise ConfigError(f"inflation: tracking_margin_m must be >= 0 (got {self.tracking_margin_m})")

    def influence_m(self, clearance_decay_m: float) -> float:
        """Beyond this clearance a cell's cost and freedom no longer depend on obstacles: a
        wall's keep-out (:meth:`planner.config.PlannerConfig.keepout_m`) plus eight decay
        lengths and half a metre."""
        return self.vehicle_radius_m + self.tracking_margin_m + 8.0 * clearance_decay_m + 0.5

    def free_threshold_m(self, resolution_m: float) -> float:
        """Smallest cell clearance at which a sampled point counts as free."""
        return self.vehicle_radius_m + resolution_m / 4.0


@dataclass(frozen=True, eq=False)
class InflatedCostmap:
    """The layer's fields for one costmap (all (rows, cols) on ``spec``).

    ``source_cost``: the costmap's uint8 grid it was inflated from. ``blocked``: cells the
    vehicle's centre region may not touch (lethal, inscribed object margins, forbidden
    unknown, outside the geofence). ``clearance_m``: conservative horizontal clearance of the
    cell, capped at :attr:`influence_m`. ``free``: the vehicle fits anywhere in the cell.
    ``cost``: 0..1 per cell (proximity to obstacles, unknown space, the map's own soft
    costs); 1 where the vehicle does not fit.
    """

    spec: GridSpec
    band: VerticalBand
    params: InflationParams
    source_cost: NDArray[np.uint8]
    blocked: NDArray[np.bool_]
    clearance_m: NDArray[np.float32]
    free: NDArray[np.bool_]
    cost: NDArray[np.float32]
    clearance_decay_m: float = DEFAULT_CLEARANCE_DECAY_M

    @property
    def influence_m(self) -> float:
        return self.params.influence_m(self.clearance_decay_m)

    @property
    def free_threshold_m(self) -> float:
        return self.params.free_threshold_m(self.spec.resolution_m)


def inflate(costmap: Costmap, params: InflationParams) -> InflatedCostmap:
    """The inflation layer of ``costmap`` for a vehicle of ``params``, over the whole grid."""
    blocked = blocked_cells(costmap, params)
    clearance, free, cost = _fields(
        blocked, costmap.cost, costmap.spec.resolution_m, params, costmap.clearance_decay_m
    )
    return InflatedCostmap(
        costmap.spec, costmap.band, params, costmap.cost.copy(), blocked, clearance, free, cost,
        costmap.clearance_decay_m,
    )


def reinflate(layer: InflatedCostmap, costmap: Costmap) -> tuple[InflatedCostmap, Bounds | None]:
    """The layer of ``costmap``, reusing ``layer`` outside the window a change can influence.

    Returns the new layer and the window whose fields were recomputed (None when the costmap
    did not change). Inflates the whole grid when its geometry, band or decay changed.
    """
    if (costmap.spec != layer.spec or costmap.band != layer.band
            or costmap.clearance_decay_m != layer.clearance_decay_m):
        return inflate(costmap, layer.params), layer.spec.bounds
    params = layer.params
    blocked = blocked_cells(costmap, params)
    changed = changed_window(blocked, layer.blocked).union(changed_window(costmap.cost, layer.source_cost))
    if changed.is_empty:
        return layer, None
    res = layer.spec.resolution_m
    reach = int(math.ceil((layer.influence_m + params.tracking_margin_m) / res)) + 2
    # Cells whose clearance can change lie within ``reach`` of a changed cell; computing their
    # distance transform needs the blocked cells within ``reach`` of those.
    a = changed.grown(reach).clipped(layer.spec.shape_rc)
    b = a.grown(reach).clipped(layer.spec.shape_rc)
    clr, fr, cst = _fields(blocked[b.slices], costmap.cost[b.slices], res, params, layer.clearance_decay_m)
    inner = a.shifted(-b.r0, -b.c0).slices
    window = a.slices
    clearance = layer.clearance_m.copy()
    free = layer.free.copy()
    cost = layer.cost.copy()
    clearance[window] = clr[inner]
    free[window] = fr[inner]
    cost[window] = cst[inner]
    new = InflatedCostmap(
        layer.spec, layer.band, params, costmap.cost.copy(), blocked, clearance, free, cost,
        layer.clearance_decay_m,
    )
    return new, a


def blocked_cells(costmap: Costmap, params: InflationParams) -> NDArray[np.bool_]:
    """Lethal and inscribed cells; unknown ones if forbidden; outside the geofence.

    INSCRIBED_INFLATED_OBSTACLE is blocked too: the margin layer writes it inside an object's
    class margin (a keep-out zone, beyond which the vehicle radius is added here).
    """
    blocked = (costmap.cost == LETHAL_OBSTACLE) | (costmap.cost == INSCRIBED_INFLATED_OBSTACLE)
    if params.unknown_cost >= 1.0:
        blocked |= costmap.cost == NO_INFORMATION
    if params.geofence_xy_m is not None:
        x0, y0, x1, y1 = params.geofence_xy_m
        X, Y = costmap.spec.cell_centers_xy()
        blocked |= (X < x0) | (X > x1) | (Y < y0) | (Y > y1)
    return blocked


def changed_window(a: NDArray[np.generic], b: NDArray[np.generic]) -> Bounds:
    """The window of the cells where a != b (empty if the arrays are equal)."""
    diff = a != b
    if not diff.any():
        return Bounds.empty()
    rows = np.flatnonzero(diff.any(axis=1))
    cols = np.flatnonzero(diff.any(axis=0))
    return Bounds(int(rows[0]), int(cols[0]), int(rows[-1]) + 1, int(cols[-1]) + 1)


def _distance_m(blocked: NDArray[np.bool_], resolution_m: float) -> NDArray[np.float64]:
    """Distance from each cell centre to the nearest blocked cell centre, metres."""
    if blocked.all():
        return np.zeros(blocked.shape)
    if not blocked.any():
        return np.full(blocked.shape, np.inf)
    return ndimage.distance_transform_edt(~blocked, sampling=resolution_m)


def _fields(
    blocked: NDArray[np.bool_], source_cost: NDArray[np.uint8], resolution_m: float,
    params: InflationParams, decay_m: float,
) -> tuple[NDArray[np.float32], NDArray[np.bool_], NDArray[np.float32]]:
    """Clearance, free and cost fields of one window (arrays of the same shape).

    Clearance is what is left beyond the keep-outs: the distance to the nearest blocked cell,
    and to the nearest blocked cell outside a class margin less the tracking margin."""
    dist = _distance_m(blocked, resolution_m)
    if params.tracking_margin_m > 0.0:
        hard = blocked & (source_cost != INSCRIBED_INFLATED_OBSTACLE)
        dist = np.minimum(dist, _distance_m(hard, resolution_m) - params.tracking_margin_m)
    # Lower bound from any point of this cell to any point of the nearest blocked cell.
    clearance = np.minimum(dist - math.sqrt(2.0) * resolution_m, params.influence_m(decay_m)).astype(np.float32)
    threshold = params.free_threshold_m(resolution_m)
    free = clearance >= threshold
    proximity = cost_decay(clearance - threshold, decay_m)
    soft = np.zeros(blocked.shape, dtype=np.float32)
    traversable = source_cost <= MAX_NON_OBSTACLE
    soft[traversable] = source_cost[traversable].astype(np.float32) / float(MAX_NON_OBSTACLE)
    soft[source_cost == NO_INFORMATION] = min(params.unknown_cost, 1.0)
    cost = np.maximum(proximity.astype(np.float32), soft)
    cost[~free] = 1.0
    return clearance, free, cost.astype(np.float32)
