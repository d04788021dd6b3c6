"""Correlative scan matchers on a probability grid (Cartographer's two search strategies).

* :func:`real_time_correlative_match`: exhaustive search over a small window around the
  prior (local SLAM); candidates are scored by the mean probability under the scan's hits,
  weighted down by their distance from the prior.
* :class:`BranchAndBoundMatcher`: the same score over a large window (loop closure), found
  exactly by branch and bound over precomputed max-pooled grids: at height ``h`` a cell holds
  the maximum of the ``2^h x 2^h`` block it anchors, so a coarse candidate's score bounds
  every finer candidate under it (Hess et al., ICRA 2016, sec. V).

The grid is a :class:`MatchGrid` with the :class:`~semmap.grid.GridSpec` cell convention
(column from x, row from y): either Cartographer's probabilities (unknown cells at the grid's
minimum) or a likelihood field of the submap's occupied cells (the default of the submaps:
robust on young submaps, smooth for the least-squares refinement).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from semmap.grid import GridSpec
from semmap.occupancy import ProbabilityGrid
from semmap.slam.pose2d import Pose2


@dataclass(frozen=True, eq=False)
class MatchGrid:
    """``probability`` (rows, cols) float32 in [0, 1]; cell (r, c) covers
    ``x in [ox + c*res, ...)``, ``y in [oy + r*res, ...)`` of the grid's frame."""

    probability: NDArray[np.float32]
    origin_xy_m: tuple[float, float]
    resolution_m: float

    @classmethod
    def from_probability_grid(cls, grid: ProbabilityGrid) -> "MatchGrid":
        """Cartographer's scoring grid: the probabilities, unknown cells at the minimum."""
        p = grid.probability()
        p = np.where(np.isnan(p), np.float32(grid.tables.min_probability), p).astype(np.float32)
        return cls(p, grid.spec.origin_xy_m, grid.spec.resolution_m)

    @classmethod
    def likelihood_field(cls, grid: ProbabilityGrid, sigma_m: float,
                         occupied_above: float = 0.5) -> "MatchGrid":
        """``exp(-d^2 / (2 sigma^2))`` with ``d`` the distance to the nearest cell whose
        probability exceeds ``occupied_above`` (1 on obstacles, falling to 0 in free and
        unknown space). Scores only agreement with obstacles: on a young submap a cell seen
        free once (p = 0.49) and a wall seen once (p = 0.55) are too alike to match against."""
        occ = grid.values > grid.tables.probability_to_value(occupied_above)
        res = grid.spec.resolution_m
        if not np.any(occ):
            return cls(np.zeros(grid.spec.shape_rc, np.float32), grid.spec.origin_xy_m, res)
        d = ndimage.distance_transform_edt(~occ) * res
        sigma = max(float(sigma_m), 0.5 * res)
        field = np.exp(-(d * d) / (2.0 * sigma * sigma)).astype(np.float32)
        return cls(field, grid.spec.origin_xy_m, res)

    @classmethod
    def from_hits(cls, hits_xy_m: NDArray[np.floating], spec: GridSpec, sigma_m: float) -> "MatchGrid":
        """A likelihood field of (N, 2) hit points over ``spec``: ``exp(-d^2 / (2 sigma^2))``
        with ``d`` the distance from each cell centre to the centroid of the hits in the
        nearest cell that has any, smoothed by a Gaussian of 0.7 cells so the ridge along a
        wall is not bumpy between centroids. Centroids keep the sub-cell position of a wall (a
        binary occupancy grid quantises it to cell centres, up to half a cell of bias), and
        the field neither saturates nor depends on how many hits a wall received. The
        default matching grid of the submaps."""
        res = spec.resolution_m
        rows, cols = spec.shape_rc
        pts = np.asarray(hits_xy_m, dtype=np.float64).reshape(-1, 2)
        rc = spec.cell_of(pts)
        ok = spec.contains_rc(rc)
        flat = rc[ok, 0] * cols + rc[ok, 1]
        if len(flat) == 0:
            return cls(np.zeros(spec.shape_rc, np.float32), spec.origin_xy_m, res)
        n = np.bincount(flat, minlength=rows * cols)
        sx = np.bincount(flat, weights=pts[ok, 0], minlength=rows * cols)
        sy = np.bincount(flat, weights=pts[ok, 1], minlength=rows * cols)
        occ = (n > 0).reshape(rows, cols)
        with np.errstate(invalid="ignore", divide="ignore"):
            cx, cy = (sx / n).reshape(rows, cols), (sy / n).reshape(rows, cols)
        idx = ndimage.distance_transform_edt(~occ, return_distances=False, return_indices=True)
        X, Y = spec.cell_centers_xy()
        d2 = (X - cx[idx[0], idx[1]]) ** 2 + (Y - cy[idx[0], idx[1]]) ** 2
        sigma = max(float(sigma_m), 0.5 * res)
        field = ndimage.gaussian_filter(np.exp(-d2 / (2.0 * sigma * sigma)), 0.7, truncate=2.0)
        return cls(field.astype(np.float32), spec.origin_xy_m, res)

    def cells_continuous(self, xy_m: NDArray[np.float64]) -> NDArray[np.float64]:
        """(N, 2) points -> (N, 2) continuous (col, row) with cell centres at integers."""
        ox, oy = self.origin_xy_m
        return np.stack([(xy_m[:, 0] - ox) / self.resolution_m - 0.5,
                         (xy_m[:, 1] - oy) / self.resolution_m - 0.5], axis=1)


def _rotated(points_xy_m: NDArray[np.float64], angles_rad: NDArray[np.float64]) -> NDArray[np.float64]:
    """(A, N, 2): the (N, 2) points rotated by each of the (A,) angles."""
    c, s = np.cos(angles_rad)[:, None], np.sin(angles_rad)[:, None]
    x, y = points_xy_m[None, :, 0], points_xy_m[None, :, 1]
    return np.stack([c * x - s * y, s * x + c * y], axis=2)


def angular_step_rad(points_xy_m: NDArray[np.float64], resolution_m: float) -> float:
    """Angle step that moves the farthest (99th percentile) point by about one cell."""
    r = float(np.percentile(np.hypot(points_xy_m[:, 0], points_xy_m[:, 1]), 99)) if len(points_xy_m) else 1.0
    r = max(r, 3.0 * resolution_m)
    return math.acos(max(-1.0, 1.0 - resolution_m**2 / (2.0 * r * r)))


def _lookup(grid: NDArray[np.float32], cols: NDArray[np.int64], rows: NDArray[np.int64]) -> NDArray[np.float32]:
    """Grid values at integer cells (any matching shapes); 0 outside the grid."""
    h, w = grid.shape
    inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    out = grid[np.clip(rows, 0, h - 1), np.clip(cols, 0, w - 1)]
    return np.where(inside, out, np.float32(0.0))


def real_time_correlative_match(
    grid: MatchGrid, points_xy_m: NDArray[np.float64], initial: Pose2,
    linear_window_m: float, angular_window_rad: float,
    translation_delta_cost_weight: float = 0.1, rotation_delta_cost_weight: float = 0.1,
) -> tuple[Pose2, float]:
    """Best pose of the (N, 2) body-frame ``points_xy_m`` in ``grid``'s frame within the window
    around ``initial`` (x, y, yaw). Returns ``(pose, score)``; score is the mean probability
    under the points (before the distance weighting)."""
    pts = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
    res = grid.resolution_m
    step = angular_step_rad(pts, res)
    n_ang = int(math.ceil(angular_window_rad / step)) if angular_window_rad > 0 else 0
    dth = np.arange(-n_ang, n_ang + 1) * step  # (A,)
    n_lin = int(math.ceil(linear_window_m / res))
    offs = np.arange(-n_lin, n_lin + 1)
    gx, gy = np.meshgrid(offs, offs)
    ox, oy = gx.ravel(), gy.ravel()  # (K,)
    rot = _rotated(pts, initial[2] + dth) + initial[:2]  # (A, N, 2)
    cc = grid.cells_continuous(rot.reshape(-1, 2)).reshape(rot.shape)
    base = np.rint(cc).astype(np.int64)  # (A, N, 2) col, row
    cols = base[:, None, :, 0] + ox[None, :, None]  # (A, K, N)
    rows = base[:, None, :, 1] + oy[None, :, None]
    score = _lookup(grid.probability, cols, rows).mean(axis=2)  # (A, K)
    dist2 = (ox**2 + oy**2) * res * res
    weight = np.exp(-(translation_delta_cost_weight * dist2[None, :]
                      + rotation_delta_cost_weight * dth[:, None] ** 2))
    a, k = np.unravel_index(int(np.argmax(score * weight)), score.shape)
    pose = np.array([initial[0] + ox[k] * res, initial[1] + oy[k] * res, initial[2] + dth[a]])
    return pose, float(score[a, k])


class BranchAndBoundMatcher:
    """Exact correlative search over a large window of one (frozen) grid.

    ``depth``: number of precomputed heights (height h pools ``2^h`` cells). Build once per
    finished submap; :meth:`match` is read-only, so one matcher serves any thread.
    """

    def __init__(self, grid: MatchGrid, depth: int = 6) -> None:
        self.grid = grid
        self.depth = max(1, int(depth))
        levels = [grid.probability.astype(np.float32)]
        for h in range(1, self.depth):
            prev = levels[-1]
            w = 1 << (h - 1)
            # Block max of 2^h anchored at (r, c) = max of four 2^(h-1) blocks.
            p = np.pad(prev, ((0, w), (0, w)))
            levels.append(np.maximum(np.maximum(p[:-w, :-w], p[w:, :-w]), np.maximum(p[:-w, w:], p[w:, w:])))
        #: (depth,) grids; levels[h][r, c] = max of probability[r:r+2^h, c:c+2^h].
        self.levels = levels

    def match(
        self, points_xy_m: NDArray[np.float64], initial: Pose2, linear_window_m: float,
        angular_window_rad: float, min_score: float,
    ) -> tuple[Pose2, float] | None:
        """Best pose of the (N, 2) body-frame points within ``+-linear_window_m`` and
        ``+-angular_window_rad`` of ``initial`` in the grid's frame, if its score (mean
        probability under the points) exceeds ``min_score``; else None."""
        pts = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
        if len(pts) == 0:
            return None
        res = self.grid.resolution_m
        step = angular_step_rad(pts, res)
        n_ang = int(math.ceil(angular_window_rad / step))
        dth = np.arange(-n_ang, n_ang + 1) * step  # (A,)
        rot = _rotated(pts, initial[2] + dth) + initial[:2]
        base = np.rint(self.grid.cells_continuous(rot.reshape(-1, 2)).reshape(rot.shape)).astype(np.int64)
        n_lin = int(math.ceil(linear_window_m / res))
        top = self.depth - 1
        size = 1 << top
        starts = np.arange(-n_lin, n_lin + 1, size)
        a0, x0, y0 = np.meshgrid(np.arange(len(dth)), starts, starts, indexing="ij")
        cand = np.stack([a0.ravel(), x0.ravel(), y0.ravel()], axis=1)  # (C, 3) angle, dx, dy
        best: list[float | tuple[int, int, int]] = [min_score, (0, 0, 0)]
        found = self._search(base, cand, top, best, n_lin)
        if not found:
            return None
        a, dx, dy = best[1]  # type: ignore[misc]
        pose = np.array([initial[0] + dx * res, initial[1] + dy * res, initial[2] + dth[a]])
        return pose, float(best[0])  # type: ignore[arg-type]

    def _scores(self, base: NDArray[np.int64], cand: NDArray[np.int64], height: int) -> NDArray[np.float32]:
        idx = base[cand[:, 0]]  # (C, N, 2)
        cols = idx[:, :, 0] + cand[:, 1:2]
        rows = idx[:, :, 1] + cand[:, 2:3]
        return _lookup(self.levels[height], cols, rows).mean(axis=1)

    def _search(self, base: NDArray[np.int64], cand: NDArray[np.int64], height: int,
                best: list[float | tuple[int, int, int]], n_lin: int) -> bool:
        """Depth-first, best child first; ``best`` = [score, (a, dx, dy)] is raised in place."""
        scores = self._scores(base, cand, height)
        order = np.argsort(-scores, kind="stable")
        found = False
        for i in order:
            s = float(scores[i])
            if s <= float(best[0]):  # type: ignore[arg-type]
                break
            a, dx, dy = (int(v) for v in cand[i])
            if height == 0:
                best[0], best[1] = s, (a, dx, dy)
                return True
            half = 1 << (height - 1)
            kids = np.array([(a, dx + ix, dy + iy) for ix in (0, half) for iy in (0, half)
                             if dx + ix <= n_lin and dy + iy <= n_lin], dtype=np.int64)
            if len(kids) and self._search(base, kids, height - 1, best, n_lin):
                found = True
        return found
