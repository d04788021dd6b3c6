"""Geometry of a 2D grid in the map frame: the one place that converts metres and cells.

Cell ``(row, col)`` covers ``x in [ox + col*r, ox + (col+1)*r)``, ``y in [oy + row*r, ...)``
where ``(ox, oy)`` is ``origin_xy_m`` (the map-frame position of the lower-left corner of cell
(0, 0)) and ``r`` the resolution. Row index grows with y (north), as in ROS ``nav_msgs``
OccupancyGrid data; pictures flip rows so north is up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class GridSpec:
    """Resolution, origin and size of a grid."""

    resolution_m: float
    origin_xy_m: tuple[float, float]
    shape_rc: tuple[int, int]  # (rows, cols)

    @classmethod
    def covering(
        cls, x_min_m: float, y_min_m: float, x_max_m: float, y_max_m: float, resolution_m: float
    ) -> "GridSpec":
        """Smallest grid of this resolution covering the rectangle."""
        cols = int(np.ceil((x_max_m - x_min_m) / resolution_m - 1e-9))
        rows = int(np.ceil((y_max_m - y_min_m) / resolution_m - 1e-9))
        return cls(resolution_m, (x_min_m, y_min_m), (max(rows, 1), max(cols, 1)))

    @property
    def rows(self) -> int:
        return self.shape_rc[0]

    @property
    def cols(self) -> int:
        return self.shape_rc[1]

    @property
    def bounds(self) -> "Bounds":
        """The whole grid as a window."""
        return Bounds(0, 0, self.rows, self.cols)

    @property
    def extent_xy_m(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) in metres."""
        ox, oy = self.origin_xy_m
        return ox, oy, ox + self.cols * self.resolution_m, oy + self.rows * self.resolution_m

    def cell_of(self, xy_m: NDArray[np.floating]) -> NDArray[np.int64]:
        """(N, 2) map-frame points -> (N, 2) integer (row, col); may lie outside the grid."""
        xy = np.asarray(xy_m, dtype=np.float64).reshape(-1, 2)
        col = np.floor((xy[:, 0] - self.origin_xy_m[0]) / self.resolution_m)
        row = np.floor((xy[:, 1] - self.origin_xy_m[1]) / self.resolution_m)
        return np.stack([row, col], axis=1).astype(np.int64)

    def center_of(self, rc: NDArray[np.integer]) -> NDArray[np.float64]:
        """(N, 2) (row, col) -> (N, 2) map-frame xy of the cell centres."""
        rc_f = np.asarray(rc, dtype=np.float64).reshape(-1, 2)
        x = self.origin_xy_m[0] + (rc_f[:, 1] + 0.5) * self.resolution_m
        y = self.origin_xy_m[1] + (rc_f[:, 0] + 0.5) * self.resolution_m
        return np.stack([x, y], axis=1)

    def contains_rc(self, rc: NDArray[np.integer]) -> NDArray[np.bool_]:
        rc = np.asarray(rc).reshape(-1, 2)
        return (rc[:, 0] >= 0) & (rc[:, 0] < self.rows) & (rc[:, 1] >= 0) & (rc[:, 1] < self.cols)

    def contains_xy(self, xy_m: NDArray[np.floating]) -> NDArray[np.bool_]:
        return self.contains_rc(self.cell_of(xy_m))

    def cell_centers_xy(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Two (rows, cols) arrays: x and y of every cell centre."""
        ox, oy = self.origin_xy_m
        r = self.resolution_m
        xs = ox + (np.arange(self.cols) + 0.5) * r
        ys = oy + (np.arange(self.rows) + 0.5) * r
        X, Y = np.meshgrid(xs, ys)
        return X, Y


def rasterize_polygon(spec: GridSpec, polygon_xy_m: NDArray[np.floating]) -> NDArray[np.bool_]:
    """(rows, cols) mask of cells whose centre lies inside a simple polygon (M, 2), any winding.

    Cells touched by the boundary count too (the polygon is dilated by half a cell), so a thin
    object never disappears between cell centres. Works on the polygon's bounding window only.
    """
    import cv2  # local: keeps ``semmap.grid`` importable without OpenCV for pure maths

    poly = np.asarray(polygon_xy_m, dtype=np.float64).reshape(-1, 2)
    mask = np.zeros(spec.shape_rc, dtype=np.uint8)
    if len(poly) < 3:
        return mask.astype(bool)
    # Sub-cell precision: OpenCV's fillPoly with shift bits on (col, row) pixel coordinates.
    shift = 4
    scale = 1 << shift
    cols = (poly[:, 0] - spec.origin_xy_m[0]) / spec.resolution_m - 0.5
    rows = (poly[:, 1] - spec.origin_xy_m[1]) / spec.resolution_m - 0.5
    pts = np.round(np.stack([cols, rows], axis=1) * scale).astype(np.int32)
    cv2.fillPoly(mask, [pts], 1, lineType=cv2.LINE_8, shift=shift)
    cv2.polylines(mask, [pts], True, 1, lineType=cv2.LINE_8, shift=shift)
    return mask.astype(bool)


@dataclass(frozen=True)
class Bounds:
    """A half-open window of cells ``rows [r0, r1) x cols [c0, c1)`` (empty when r1 <= r0)."""

    r0: int
    c0: int
    r1: int
    c1: int

    @classmethod
    def empty(cls) -> "Bounds":
        return cls(0, 0, 0, 0)

    @property
    def is_empty(self) -> bool:
        return self.r1 <= self.r0 or self.c1 <= self.c0

    def union(self, other: "Bounds") -> "Bounds":
        if self.is_empty:
            return other
        if other.is_empty:
            return self
        return Bounds(
            min(self.r0, other.r0), min(self.c0, other.c0),
            max(self.r1, other.r1), max(self.c1, other.c1),
        )

    def shifted(self, d_rows: int, d_cols: int) -> "Bounds":
        if self.is_empty:
            return self
        return Bounds(self.r0 + d_rows, self.c0 + d_cols, self.r1 + d_rows, self.c1 + d_cols)

    def grown(self, cells: int) -> "Bounds":
        """The window widened by ``cells`` on every side (not clipped to a grid)."""
        if self.is_empty:
            return self
        return Bounds(self.r0 - cells, self.c0 - cells, self.r1 + cells, self.c1 + cells)

    def clipped(self, shape_rc: tuple[int, int]) -> "Bounds":
        r0, c0 = max(self.r0, 0), max(self.c0, 0)
        r1, c1 = min(self.r1, shape_rc[0]), min(self.c1, shape_rc[1])
        return Bounds(r0, c0, r1, c1) if (r1 > r0 and c1 > c0) else Bounds.empty()

    @property
    def slices(self) -> tuple[slice, slice]:
        return slice(self.r0, self.r1), slice(self.c0, self.c1)
