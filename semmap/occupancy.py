"""Cartographer-style 2D probability grid with precomputed odds-update tables.

Each cell holds a ``uint16`` value: 0 is *unknown* (never observed), 1..32767 encode the
occupancy probability linearly in ``[min_probability, max_probability]`` (Cartographer's
``ProbabilityToValue``). An observation multiplies the cell's odds by the hit or miss odds;
the result is looked up in a table indexed by the current value, so an update is one fancy
index per cell class and clamping comes for free (the table's outputs are clamped values).

Cartographer marks updated cells with ``kUpdateMarker`` so that each cell is updated at most
once per scan; here the same guarantee comes from set arithmetic on the scan's cells (hits are
unique, misses exclude hit cells), which is cheaper in numpy than a marker pass.

Free space of a scan is rasterised as the polygon swept by its rays (``cv2.fillPoly`` over the
scan's window), not by stepping along each ray: the polygon is exact up to the angular spacing
of the rays and costs one C call per run of valid columns.

The grid covers :attr:`ProbabilityGrid.spec` (a :class:`~semmap.grid.GridSpec`) and grows in
whole chunks when a scan reaches past its edge, unless it was built ``fixed_size``.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
from numpy.typing import NDArray

from semmap.errors import MapError
from semmap.grid import Bounds, GridSpec

log = logging.getLogger(__name__)

UNKNOWN_VALUE = 0
MIN_VALUE = 1
MAX_VALUE = 32767
#: Number of distinct uint16 cell values (0 = unknown, 1..32767 = probability).
N_VALUES = MAX_VALUE + 1


def odds(probability: float | NDArray[np.float64]) -> NDArray[np.float64]:
    """p / (1 - p)."""
    p = np.asarray(probability, dtype=np.float64)
    return p / (1.0 - p)


def probability_from_odds(odds_value: float | NDArray[np.float64]) -> NDArray[np.float64]:
    """odds / (1 + odds)."""
    o = np.asarray(odds_value, dtype=np.float64)
    return o / (1.0 + o)


class ProbabilityTables:
    """Value <-> probability conversion and the hit/miss update tables for one parameter set."""

    def __init__(
        self, hit_probability: float = 0.55, miss_probability: float = 0.49,
        min_probability: float = 0.12, max_probability: float = 0.97,
    ) -> None:
        if not 0.0 < min_probability < max_probability < 1.0:
            raise MapError(
                f"need 0 < min_probability < max_probability < 1 (got {min_probability}, {max_probability})"
            )
        if not 0.5 < hit_probability < 1.0:
            raise MapError(f"hit_probability must be in (0.5, 1) (got {hit_probability})")
        if not 0.0 < miss_probability < 0.5:
            raise MapError(f"miss_probability must be in (0, 0.5) (got {miss_probability})")
        self.hit_probability = hit_probability
        self.miss_probability = miss_probability
        self.min_probability = min_probability
        self.max_probability = max_probability
        values = np.arange(N_VALUES)
        #: (32768,) float32 probability of each value; NaN for the unknown value 0.
        self.value_to_probability = np.full(N_VALUES, np.nan, dtype=np.float32)
        self.value_to_probability[1:] = self._value_to_p(values[1:])
        self.hit_table = self._update_table(float(odds(hit_probability)))
        self.miss_table = self._update_table(float(odds(miss_probability)))

    def _value_to_p(self, value: NDArray[np.integer]) -> NDArray[np.float64]:
        span = self.max_probability - self.min_probability
        return self.min_probability + (np.asarray(value, np.float64) - MIN_VALUE) * span / (MAX_VALUE - MIN_VALUE)

    def probability_to_value(self, probability: float | NDArray[np.floating]) -> NDArray[np.uint16]:
        """Probabilities (any shape) -> uint16 values 1..32767, clamped to [min, max]."""
        p = np.clip(np.asarray(probability, np.float64), self.min_probability, self.max_probability)
        span = self.max_probability - self.min_probability
        v = MIN_VALUE + np.rint((p - self.min_probability) * (MAX_VALUE - MIN_VALUE) / span)
        return v.astype(np.uint16)

    def _update_table(self, odds_factor: float) -> NDArray[np.uint16]:
        """(32768,) uint16: the value after multiplying the odds by ``odds_factor``.

        The unknown value 0 is treated as p = 0.5 (odds 1), so a first observation lands on
        exactly the hit or miss probability, as in Cartographer.
        """
        p = np.empty(N_VALUES, np.float64)
        p[0] = 0.5
        p[1:] = self._value_to_p(np.arange(1, N_VALUES))
        return self.probability_to_value(probability_from_odds(odds(p) * odds_factor))


class ProbabilityGrid:
    """A growing 2D occupancy probability grid in the map frame.

    ``values``: (rows, cols) uint16 as described in the module docstring. Use :meth:`apply`
    to update explicit cells and :meth:`insert_scan` to update from a scan's rays.
    """

    def __init__(
        self, spec: GridSpec, tables: ProbabilityTables | None = None,
        fixed_size: bool = False, grow_chunk_m: float = 5.0,
    ) -> None:
        self.spec = spec
        self.tables = tables or ProbabilityTables()
        self.fixed_size = fixed_size
        self.grow_chunk_m = grow_chunk_m
        self.values = np.zeros(spec.shape_rc, dtype=np.uint16)  # (rows, cols)

    def copy(self) -> "ProbabilityGrid":
        """A deep copy (the tables are shared: they are read-only)."""
        out = ProbabilityGrid(self.spec, self.tables, self.fixed_size, self.grow_chunk_m)
        out.values = self.values.copy()
        return out

    # --- reading ----------------------------------------------------------------------

    @property
    def known(self) -> NDArray[np.bool_]:
        """(rows, cols) True where the cell has been observed at least once."""
        return self.values != UNKNOWN_VALUE

    def probability(self) -> NDArray[np.float32]:
        """(rows, cols) float32 occupancy probability; NaN where unknown."""
        return self.tables.value_to_probability[self.values]

    def probability_u8(self) -> tuple[NDArray[np.uint8], NDArray[np.bool_]]:
        """(rows, cols) uint8 with 0..255 for 0..100 % and the (rows, cols) ``known`` mask.

        Unknown cells are a separate mask because all 256 values mean a probability.
        """
        lut = np.zeros(N_VALUES, dtype=np.uint8)
        lut[1:] = np.rint(self.tables.value_to_probability[1:] * 255.0).astype(np.uint8)
        return lut[self.values], self.known

    def probability_at_xy(self, xy_m: NDArray[np.floating]) -> NDArray[np.float32]:
        """(N,) probability at (N, 2) map points; NaN where unknown or outside the grid."""
        rc = self.spec.cell_of(xy_m)
        inside = self.spec.contains_rc(rc)
        out = np.full(len(rc), np.nan, dtype=np.float32)
        out[inside] = self.tables.value_to_probability[self.values[rc[inside, 0], rc[inside, 1]]]
        return out

    def set_values(self, values: NDArray[np.uint16]) -> None:
        """Replace the cell values (e.g. after loading); shape must match the spec."""
        v = np.asarray(values)
        if v.shape != self.spec.shape_rc or v.dtype != np.uint16:
            raise MapError(
                f"grid values must be uint16 {self.spec.shape_rc}, got {v.dtype} {v.shape}"
            )
        self.values = v.copy()

    # --- growing ----------------------------------------------------------------------

    def ensure_contains(self, x_min_m: float, y_min_m: float, x_max_m: float, y_max_m: float) -> tuple[int, int]:
        """Grow (in chunks of ``grow_chunk_m``) until the rectangle lies inside the grid.

        Returns the (rows, cols) shift of existing cell indices (non-zero when the grid grew
        towards negative x or y). A fixed-size grid never grows; callers clip instead.
        """
        if self.fixed_size:
            return 0, 0
        r = self.spec.resolution_m
        ox, oy = self.spec.origin_xy_m
        ex0, ey0, ex1, ey1 = self.spec.extent_xy_m
        chunk = max(1, int(round(self.grow_chunk_m / r)))

        def cells_needed(gap_m: float) -> int:
            if gap_m <= 0.0:
                return 0
            return int(np.ceil(gap_m / r / chunk)) * chunk

        add_left = cells_needed(ex0 - x_min_m)
        add_right = cells_needed(x_max_m - ex1)
        add_bottom = cells_needed(ey0 - y_min_m)
        add_top = cells_needed(y_max_m - ey1)
        if not (add_left or add_right or add_bottom or add_top):
            return 0, 0
        rows, cols = self.spec.shape_rc
        new_shape = (rows + add_bottom + add_top, cols + add_left + add_right)
        new_values = np.zeros(new_shape, dtype=np.uint16)
        new_values[add_bottom:add_bottom + rows, add_left:add_left + cols] = self.values
        self.values = new_values
        self.spec = GridSpec(r, (ox - add_left * r, oy - add_bottom * r), new_shape)
        log.debug("grid grew to %dx%d cells (origin %.2f, %.2f)", new_shape[0], new_shape[1], *self.spec.origin_xy_m)
        return add_bottom, add_left

    # --- updating ---------------------------------------------------------------------

    def apply(self, hit_rc: NDArray[np.integer], miss_rc: NDArray[np.integer]) -> Bounds:
        """Apply one scan's hits and misses: each cell is updated at most once.

        ``hit_rc``/``miss_rc``: (N, 2) (row, col) cells; duplicates and cells outside the grid
        are ignored; a cell that is both a hit and a miss counts as a hit. Returns the window
        of touched cells.
        """
        hit_flat = self._flat_unique(hit_rc)
        miss_flat = self._flat_unique(miss_rc)
        if len(hit_flat) and len(miss_flat):
            miss_flat = miss_flat[~np.isin(miss_flat, hit_flat, assume_unique=True)]
        return self._apply_flat(hit_flat, miss_flat)

    def _apply_flat(self, hit_flat: NDArray[np.int64], miss_flat: NDArray[np.int64]) -> Bounds:
        """:meth:`apply` on flat cell indices already unique, inside the grid and disjoint."""
        cols = self.spec.cols
        flat = self.values.reshape(-1)
        if len(hit_flat):
            flat[hit_flat] = self.tables.hit_table[flat[hit_flat]]
        if len(miss_flat):
            flat[miss_flat] = self.tables.miss_table[flat[miss_flat]]
        touched = np.concatenate([hit_flat, miss_flat])
        if not len(touched):
            return Bounds.empty()
        r, c = np.divmod(touched, cols)
        return Bounds(int(r.min()), int(c.min()), int(r.max()) + 1, int(c.max()) + 1)

    def _flat_unique(self, rc: NDArray[np.integer]) -> NDArray[np.int64]:
        rc = np.asarray(rc, dtype=np.int64).reshape(-1, 2)
        rc = rc[self.spec.contains_rc(rc)]
        return np.unique(rc[:, 0] * self.spec.cols + rc[:, 1])

    def insert_scan(
        self, origin_xy_m: NDArray[np.floating], near_xy_m: NDArray[np.floating],
        far_xy_m: NDArray[np.floating], hit_xy_m: NDArray[np.floating],
        is_hit: NDArray[np.bool_], valid: NDArray[np.bool_],
    ) -> Bounds:
        """Update from a fan of rays (one per image column, ordered by bearing).

        ``near_xy_m``/``far_xy_m``: (W, 2) where each ray's free part starts and ends (the
        start is the sensor position when the sensor is inside the scan band).
        ``hit_xy_m``: (W, 2) obstacle point of rays with ``is_hit`` (W,). ``valid``: (W,) the ray
        carries information. Free space is the polygon swept by consecutive valid rays; hit
        cells win over free cells. Grows the grid first unless it is fixed. Returns the
        touched window (after any growth, in the new indices).
        """
        near = np.asarray(near_xy_m, np.float64).reshape(-1, 2)
        far = np.asarray(far_xy_m, np.float64).reshape(-1, 2)
        hits = np.asarray(hit_xy_m, np.float64).reshape(-1, 2)
        ok = np.asarray(valid, bool).reshape(-1)
        hit = np.asarray(is_hit, bool).reshape(-1) & ok
        if not np.any(ok):
            return Bounds.empty()
        pts = np.concatenate([near[ok], far[ok], hits[hit], np.asarray(origin_xy_m, np.float64).reshape(1, 2)])
        pad = 2.0 * self.spec.resolution_m
        lo, hi = pts.min(axis=0) - pad, pts.max(axis=0) + pad
        self.ensure_contains(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
        spec = self.spec
        window = Bounds(*spec.cell_of(lo[None])[0], *(spec.cell_of(hi[None])[0] + 1)).clipped(spec.shape_rc)
        if window.is_empty:
            return Bounds.empty()
        free = _fill_runs(spec, window, near, far, ok)  # (window rows, window cols) bool
        hit_flat = self._flat_unique(spec.cell_of(hits[hit]))
        # A hit cell is no miss (as in apply); the misses come from the window's mask, so
        # they are unique, sorted and inside the grid without a sort of their own.
        hr, hc = np.divmod(hit_flat, spec.cols)
        hr -= window.r0
        hc -= window.c0
        in_window = (hr >= 0) & (hr < free.shape[0]) & (hc >= 0) & (hc < free.shape[1])
        free[hr[in_window], hc[in_window]] = False
        fr, fc = np.nonzero(free)
        miss_flat = (fr + window.r0) * spec.cols + (fc + window.c0)
        return self._apply_flat(hit_flat, miss_flat.astype(np.int64, copy=False))


def _fill_runs(
    spec: GridSpec, window: Bounds, near: NDArray[np.float64], far: NDArray[np.float64],
    valid: NDArray[np.bool_],
) -> NDArray[np.bool_]:
    """Rasterise the free polygons of each run of consecutive valid rays into the window."""
    mask = np.zeros((window.r1 - window.r0, window.c1 - window.c0), dtype=np.uint8)
    shift = 4
    scale = 1 << shift

    def to_px(xy: NDArray[np.float64]) -> NDArray[np.int32]:
        # fillPoly works on pixel centres at integer coordinates: cell (r, c) centre -> (c, r).
        col = (xy[:, 0] - spec.origin_xy_m[0]) / spec.resolution_m - 0.5 - window.c0
        row = (xy[:, 1] - spec.origin_xy_m[1]) / spec.resolution_m - 0.5 - window.r0
        return np.rint(np.stack([col, row], axis=1) * scale).astype(np.int32)

    idx = np.flatnonzero(valid)
    breaks = np.flatnonzero(np.diff(idx) > 1) + 1
    for run in np.split(idx, breaks):
        if len(run) == 0:
            continue
        if len(run) == 1:
            # A lone ray still clears the cells along it.
            cv2.line(mask, tuple(to_px(near[run])[0]), tuple(to_px(far[run])[0]), 1, 1, cv2.LINE_8, shift)
            continue
        # One call per run: fillPoly's parity rule would cancel overlapping runs.
        cv2.fillPoly(mask, [to_px(np.concatenate([near[run], far[run][::-1]]))], 1, cv2.LINE_8, shift)
    return mask.astype(bool)
