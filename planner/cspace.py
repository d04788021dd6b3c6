"""The configuration space of a multicopter at one flight altitude, and the checks on it.

The map owns every cost: its layers paint footprints, class margins and the altitude rule
(:mod:`semmap.layers`), and its inflation layer (:mod:`semmap.inflation`) adds the vehicle's
radius and tracking margin as nav2's inflation layer does. A :class:`CSpace` is one version of
that inflated costmap with the planner's queries on it: a state check is one array index, a
motion check samples the segment every half cell in one numpy call. :func:`update_cspace`
re-inflates only the window a map change can influence.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from semmap.costmap import Costmap, VerticalBand
from semmap.grid import Bounds, GridSpec
from semmap.inflation import InflatedCostmap, InflationParams, inflate, reinflate

#: A point (x, y) in the map frame, metres: a (2,) array or any pair of numbers.
XYLike = NDArray[np.floating] | Sequence[float] | tuple[float, float]


@dataclass(frozen=True, eq=False)
class CSpace:
    """One map version's inflated costmap (``layer``) and the queries the planner asks of it."""

    layer: InflatedCostmap
    version: int = 0

    @property
    def spec(self) -> GridSpec:
        return self.layer.spec

    @property
    def band(self) -> VerticalBand:
        return self.layer.band

    @property
    def params(self) -> InflationParams:
        return self.layer.params

    @property
    def free(self) -> NDArray[np.bool_]:
        return self.layer.free

    @property
    def cost(self) -> NDArray[np.float32]:
        return self.layer.cost

    @property
    def clearance_m(self) -> NDArray[np.float32]:
        return self.layer.clearance_m

    @property
    def free_threshold_m(self) -> float:
        return self.layer.free_threshold_m

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


def build_cspace(costmap: Costmap, params: InflationParams, version: int = 0) -> CSpace:
    """The configuration space of ``costmap`` for a vehicle of ``params``."""
    return CSpace(inflate(costmap, params), version)


def update_cspace(cs: CSpace, costmap: Costmap, version: int) -> tuple[CSpace, Bounds | None]:
    """The configuration space of ``costmap``, reusing ``cs`` outside the changed window.

    Returns the new space and the window whose fields changed (None when nothing did)."""
    layer, window = reinflate(cs.layer, costmap)
    return CSpace(layer, version), window
