"""The configuration space of a multicopter at one flight altitude, as precomputed fields.

The costmap arrives with every object already costed by the map's layers
(:mod:`semmap.layers`: footprints, class margins, the altitude rule, their decay);
:func:`build_cspace` only adds the vehicle: the blocked cells (lethal and inscribed, plus
unknown when unknown space is forbidden, plus outside the geofence), a clearance field in
metres from a Euclidean distance transform, the boolean free grid for the vehicle's radius
and a 0..1 traversal cost per cell whose proximity term decays with the costmap's
``clearance_decay_m`` (:func:`semmap.layers.cost_decay`).

All validity checks are lookups in these fields, vectorised over many points: a state check
is one array index, a motion check samples the segment every half cell in one numpy call.
:func:`update_cspace` recomputes the fields only in the window a map change can influence,
so replanning after a new object appears does not pay for the whole map again.

Clearance is conservative: ``clearance_m`` of a cell is a lower bound on the horizontal
distance from *any* point of the cell to the nearest blocked cell's square (centre distance
minus one cell diagonal; from a blocked cell outside a class margin, less the tracking
margin too), and a point is free when that bound is at least the vehicle radius plus a quarter
cell (the largest gap between motion samples spaced half a cell apart).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
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
from semmap.errors import PlanningError
from semmap.grid import GridSpec
from semmap.layers import cost_decay

#: A point (x, y) in the map frame, metres: a (2,) array or any pair of numbers.
XYLike = NDArray[np.floating] | Sequence[float] | tuple[float, float]


@dataclass(frozen=True)
class CSpaceParams:
    """How a costmap becomes a configuration space.

    ``vehicle_radius_m``: horizontal radius of the vehicle. ``tracking_margin_m``: kept beyond
    the radius from every blocked cell outside an object's class margin (walls, unclassified
    clutter, the geofence), because the autopilot flies a few centimetres off the commanded
    path; a class margin already keeps the vehicle that far from its object when it is at
    least this wide. ``unknown_cost`` (0..1): cost of an unknown cell relative to the highest
    traversable cost; 1 forbids unknown space. ``geofence_xy_m``: the vehicle (its whole
    radius) stays inside it.
    """

    vehicle_radius_m: float
    tracking_margin_m: float = 0.0
    unknown_cost: float = 0.5
    #: [x_min, y_min, x_max, y_max] in the map frame; cells outside it are blocked.
    geofence_xy_m: tuple[float, float, float, float] | None = None

    def influence_m(self, clearance_decay_m: float) -> float:
        """Beyond this clearance a cell's cost and freedom no longer depend on obstacles: a
        wall's keep-out (:meth:`planner.config.PlannerConfig.keepout_m`) plus eight decay
        lengths and half a metre."""
        return self.vehicle_radius_m + self.tracking_margin_m + 8.0 * clearance_decay_m + 0.5


@dataclass(frozen=True, eq=False)
class CSpace:
    """Precomputed fields for one map version at one altitude (all (rows, cols) on ``spec``).

    ``blocked``: cells the vehicle's centre region may not touch (lethal, inscribed object
    margins, forbidden unknown). ``clearance_m``: conservative horizontal clearance of the
    cell, capped at :attr:`influence_m`. ``free``: the vehicle fits anywhere in the cell.
    ``cost``: traversal cost 0..1 per cell (proximity to obstacles, unknown space, the map's
    own soft costs). ``source_cost``: the costmap's uint8 grid it was built from.
    """

    spec: GridSpec
    band: VerticalBand
    params: CSpaceParams
    source_cost: NDArray[np.uint8]
    blocked: NDArray[np.bool_]
    clearance_m: NDArray[np.float32]
    free: NDArray[np.bool_]
    cost: NDArray[np.float32]
    version: int = 0
    #: The costmap's decay of cost beyond a keep-out zone, which the proximity cost follows.
    clearance_decay_m: float = DEFAULT_CLEARANCE_DECAY_M

    @property
    def influence_m(self) -> float:
        return self.params.influence_m(self.clearance_decay_m)

    @property
    def free_threshold_m(self) -> float:
        """Smallest cell clearance at which a sampled point counts as free."""
        return self.params.vehicle_radius_m + self.spec.resolution_m / 4.0

    @property
    def motion_step_m(self) -> float:
        """Spacing of the samples a motion check takes along a segment (half a cell)."""
        return self.spec.resolution_m / 2.0

    # --- point queries ---------------------------------------------------------------

    def cells(self, xy_m: NDArray[np.floating]) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        """(N, 2) map points -> (N, 2) (row, col) clipped into the grid, and (N,) inside mask."""
        rc = self.spec.cell_of(xy_m)
        inside = self.spec.contains_rc(rc)
        rc[:, 0] = np.clip(rc[:, 0], 0, self.spec.rows - 1)
        rc[:, 1] = np.clip(rc[:, 1], 0, self.spec.cols - 1)
        return rc, inside

    def is_free(self, xy_m: NDArray[np.floating]) -> NDArray[np.bool_]:
        """(N,) True where the vehicle centred at the (N, 2) map point fits; outside = False."""
        rc, inside = self.cells(xy_m)
        return inside & self.free[rc[:, 0], rc[:, 1]]

    def clearance_at(self, xy_m: NDArray[np.floating]) -> NDArray[np.float32]:
        """(N,) conservative clearance in metres at (N, 2) map points; -inf outside the map."""
        rc, inside = self.cells(xy_m)
        out = self.clearance_m[rc[:, 0], rc[:, 1]].copy()
        out[~inside] = -np.inf
        return out

    def cost_at(self, xy_m: NDArray[np.floating]) -> NDArray[np.float32]:
        """(N,) traversal cost 0..1 at (N, 2) map points (1 outside the map)."""
        rc, inside = self.cells(xy_m)
        out = self.cost[rc[:, 0], rc[:, 1]].copy()
        out[~inside] = 1.0
        return out

    # --- segments and paths -------------------------------------------------------------

    def sample_segment(self, a_xy_m: NDArray[np.floating], b_xy_m: NDArray[np.floating]) -> NDArray[np.float64]:
        """(S, 2) points from a to b inclusive, at most half a cell apart."""
        a = np.asarray(a_xy_m, dtype=np.float64).reshape(2)
        b = np.asarray(b_xy_m, dtype=np.float64).reshape(2)
        n = max(1, int(math.ceil(float(np.hypot(*(b - a))) / self.motion_step_m)))
        t = np.linspace(0.0, 1.0, n + 1)[:, None]
        return a + t * (b - a)

    def _segment_flat(self, a_xy_m: XYLike, b_xy_m: XYLike) -> tuple[NDArray[np.int64] | None, float]:
        """Flat cell indices of the half-cell samples of a -> b (None if any is outside), length."""
        res = self.spec.resolution_m
        ox, oy = self.spec.origin_xy_m
        rows, cols = self.spec.shape_rc
        # Grid coordinates (in cells) of both ends; the segment is inside iff both ends are.
        ac, ar = (float(a_xy_m[0]) - ox) / res, (float(a_xy_m[1]) - oy) / res
        bc, br = (float(b_xy_m[0]) - ox) / res, (float(b_xy_m[1]) - oy) / res
        length = math.hypot(bc - ac, br - ar) * res
        if min(ac, bc, ar, br) < 0.0 or max(ac, bc) >= cols or max(ar, br) >= rows:
            return None, length
        n = max(1, int(math.ceil(length / self.motion_step_m)))
        t = _unit_steps(n)
        col = (ac + t * (bc - ac)).astype(np.int64)
        row = (ar + t * (br - ar)).astype(np.int64)
        return row * cols + col, length

    def segment_free(self, a_xy_m: XYLike, b_xy_m: XYLike) -> bool:
        """True if the vehicle can fly the straight segment a -> b (map frame, metres)."""
        flat, _ = self._segment_flat(a_xy_m, b_xy_m)
        return flat is not None and bool(self.free.ravel()[flat].all())

    def segment_eval(self, a_xy_m: XYLike, b_xy_m: XYLike) -> tuple[bool, float, float]:
        """(free, length m, integral of the cell cost m) of the straight segment a -> b."""
        flat, length = self._segment_flat(a_xy_m, b_xy_m)
        if flat is None:
            return False, length, length
        if not self.free.ravel()[flat].all():
            return False, length, length
        return True, length, float(self.cost.ravel()[flat].sum()) / len(flat) * length

    def segment_cost_integral(self, a_xy_m: XYLike, b_xy_m: XYLike) -> float:
        """Integral of the cell cost along a -> b, metres (mean sampled cost times length)."""
        return self.segment_eval(a_xy_m, b_xy_m)[2]

    def densify(self, path_xy_m: NDArray[np.floating]) -> NDArray[np.float64]:
        """(K, 2) polyline -> (M, 2) points at most half a cell apart (vertices kept)."""
        p = np.asarray(path_xy_m, dtype=np.float64).reshape(-1, 2)
        if len(p) < 2:
            return p.copy()
        seg = np.diff(p, axis=0)
        n = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / self.motion_step_m)).astype(np.int64)
        idx = np.repeat(np.arange(len(seg)), n)
        # Fraction along each segment of every sample, excluding the segment's end point.
        frac = (np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)) / np.repeat(n, n)
        pts = p[idx] + frac[:, None] * seg[idx]
        return np.vstack([pts, p[-1:]])

    def path_free(self, path_xy_m: NDArray[np.floating]) -> bool:
        """True if every segment of the (K, 2) polyline is free."""
        return bool(np.all(self.is_free(self.densify(path_xy_m))))

    def escape_point(self, xy_m: NDArray[np.floating], extra_m: float = 0.05) -> NDArray[np.float64] | None:
        """The nearest cell centre to ``xy_m`` where the vehicle fits with ``extra_m`` to
        spare (where to back off to when the start is too close to an obstacle); None if none."""
        rows, cols = np.nonzero(self.free & (self.clearance_m >= self.free_threshold_m + extra_m))
        if len(rows) == 0:
            return None
        spec = self.spec
        cx = spec.origin_xy_m[0] + (cols + 0.5) * spec.resolution_m
        cy = spec.origin_xy_m[1] + (rows + 0.5) * spec.resolution_m
        k = int(np.argmin((cx - xy_m[0]) ** 2 + (cy - xy_m[1]) ** 2))
        return np.array([cx[k], cy[k]])

    def first_blocked_index(self, path_xy_m: NDArray[np.floating]) -> int:
        """Index of the first segment of the (K, 2) polyline that is not free; -1 if none."""
        p = np.asarray(path_xy_m, dtype=np.float64).reshape(-1, 2)
        for i in range(len(p) - 1):
            if not self.segment_free(p[i], p[i + 1]):
                return i
        if len(p) == 1 and not self.is_free(p)[0]:
            return 0
        return -1

    def path_cost(self, path_xy_m: NDArray[np.floating], cost_weight: float) -> float:
        """Objective of a (K, 2) polyline: length + weight * integral of the cell cost, metres."""
        p = np.asarray(path_xy_m, dtype=np.float64).reshape(-1, 2)
        total = 0.0
        for a, b in zip(p[:-1], p[1:], strict=True):
            total += float(np.hypot(*(b - a))) + cost_weight * self.segment_cost_integral(a, b)
        return total


_STEPS_CACHE: dict[int, NDArray[np.float64]] = {}


def _unit_steps(n: int) -> NDArray[np.float64]:
    """(n + 1,) evenly spaced fractions 0..1 (cached: motion checks ask for the same n often)."""
    t = _STEPS_CACHE.get(n)
    if t is None:
        t = np.linspace(0.0, 1.0, n + 1)
        t.setflags(write=False)
        if len(_STEPS_CACHE) < 4096:
            _STEPS_CACHE[n] = t
    return t


def _blocked_mask(costmap: Costmap, params: CSpaceParams) -> NDArray[np.bool_]:
    """Lethal and inscribed cells; unknown ones if forbidden; outside the geofence.

    INSCRIBED_INFLATED_OBSTACLE is blocked too: the map's margin layer writes it inside an
    object's class margin (a keep-out zone, beyond which the vehicle radius is added here).
    """
    blocked = (costmap.cost == LETHAL_OBSTACLE) | (costmap.cost == INSCRIBED_INFLATED_OBSTACLE)
    if params.unknown_cost >= 1.0:
        blocked |= costmap.cost == NO_INFORMATION
    if params.geofence_xy_m is not None:
        x0, y0, x1, y1 = params.geofence_xy_m
        X, Y = costmap.spec.cell_centers_xy()
        blocked |= (X < x0) | (X > x1) | (Y < y0) | (Y > y1)
    return blocked


def _distance_m(blocked: NDArray[np.bool_], resolution_m: float) -> NDArray[np.float64]:
    """Distance from each cell centre to the nearest blocked cell centre, metres."""
    if blocked.all():
        return np.zeros(blocked.shape)
    if not blocked.any():
        return np.full(blocked.shape, np.inf)
    return ndimage.distance_transform_edt(~blocked, sampling=resolution_m)


def _fields(
    blocked: NDArray[np.bool_], source_cost: NDArray[np.uint8], resolution_m: float,
    params: CSpaceParams, decay_m: float,
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
    threshold = params.vehicle_radius_m + resolution_m / 4.0
    free = clearance >= threshold
    proximity = cost_decay(clearance - threshold, decay_m)
    soft = np.zeros(blocked.shape, dtype=np.float32)
    traversable = source_cost <= MAX_NON_OBSTACLE
    soft[traversable] = source_cost[traversable].astype(np.float32) / float(MAX_NON_OBSTACLE)
    soft[source_cost == NO_INFORMATION] = min(params.unknown_cost, 1.0)
    cost = np.maximum(proximity.astype(np.float32), soft)
    cost[~free] = 1.0
    return clearance, free, cost.astype(np.float32)


def build_cspace(costmap: Costmap, params: CSpaceParams, version: int = 0) -> CSpace:
    """Precompute the configuration space of ``costmap`` for a vehicle of ``params``."""
    if params.vehicle_radius_m <= 0.0:
        raise PlanningError(f"vehicle_radius_m must be > 0 (got {params.vehicle_radius_m})")
    if not params.tracking_margin_m >= 0.0:
        raise PlanningError(f"tracking_margin_m must be >= 0 (got {params.tracking_margin_m})")
    decay = costmap.clearance_decay_m
    blocked = _blocked_mask(costmap, params)
    clearance, free, cost = _fields(blocked, costmap.cost, costmap.spec.resolution_m, params, decay)
    return CSpace(
        costmap.spec, costmap.band, params, costmap.cost.copy(), blocked, clearance, free, cost,
        version, decay,
    )


def changed_window(
    a: NDArray[np.generic], b: NDArray[np.generic]
) -> tuple[int, int, int, int] | None:
    """Bounding box (r0, r1, c0, c1), end-exclusive, of the cells where a != b; None if equal."""
    diff = a != b
    if not diff.any():
        return None
    rows = np.flatnonzero(diff.any(axis=1))
    cols = np.flatnonzero(diff.any(axis=0))
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def update_cspace(
    cs: CSpace, costmap: Costmap, version: int
) -> tuple[CSpace, tuple[int, int, int, int] | None]:
    """The configuration space of ``costmap``, reusing ``cs`` outside the changed window.

    Returns the new space and the window (r0, r1, c0, c1) whose fields changed (None when
    nothing did). Falls back to a full rebuild when the grid geometry or band changed.
    """
    if costmap.spec != cs.spec or costmap.band != cs.band or costmap.clearance_decay_m != cs.clearance_decay_m:
        return build_cspace(costmap, cs.params, version), (0, cs.spec.rows, 0, cs.spec.cols)
    blocked = _blocked_mask(costmap, cs.params)
    changed = _union_window(
        changed_window(blocked, cs.blocked), changed_window(costmap.cost, cs.source_cost)
    )
    if changed is None:
        return dataclasses.replace(cs, version=version), None
    res = cs.spec.resolution_m
    reach = int(math.ceil((cs.influence_m + cs.params.tracking_margin_m) / res)) + 2
    rows, cols = cs.spec.shape_rc
    r0, r1, c0, c1 = changed
    # Cells whose clearance can change lie within ``reach`` of a changed cell; computing their
    # distance transform needs the blocked cells within ``reach`` of those.
    a = (max(0, r0 - reach), min(rows, r1 + reach), max(0, c0 - reach), min(cols, c1 + reach))
    b = (max(0, a[0] - reach), min(rows, a[1] + reach), max(0, a[2] - reach), min(cols, a[3] + reach))
    sub_blocked = blocked[b[0]:b[1], b[2]:b[3]]
    sub_cost = costmap.cost[b[0]:b[1], b[2]:b[3]]
    clr, fr, cst = _fields(sub_blocked, sub_cost, res, cs.params, cs.clearance_decay_m)
    inner = (slice(a[0] - b[0], a[1] - b[0]), slice(a[2] - b[2], a[3] - b[2]))
    window = (slice(a[0], a[1]), slice(a[2], a[3]))
    clearance = cs.clearance_m.copy()
    free = cs.free.copy()
    cost = cs.cost.copy()
    clearance[window] = clr[inner]
    free[window] = fr[inner]
    cost[window] = cst[inner]
    new = CSpace(cs.spec, cs.band, cs.params, costmap.cost.copy(), blocked, clearance, free, cost,
                 version, cs.clearance_decay_m)
    return new, a


def _union_window(
    a: tuple[int, int, int, int] | None, b: tuple[int, int, int, int] | None
) -> tuple[int, int, int, int] | None:
    if a is None:
        return b
    if b is None:
        return a
    return min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3])
