"""Grid shortest paths on a configuration space, and any-angle post-processing.

The planner's first path comes from here: Dijkstra (SciPy's compiled ``csgraph``) on an
8-connected graph over the free cells, optionally on a coarser grid whose node is free only
if every fine cell in its block is, with edge weights ``step * (1 + w * mean cost)``. The
graph's structure depends only on the grid shape and is cached; a map change only rewrites
the weights of the changed window. Dijkstra also proves disconnection (the goal's distance
is infinite) and gives the reachable set used to snap goals.

:func:`shortcut` turns a grid path into an any-angle path (greedy farthest visible vertex,
accepted only where the objective does not get worse) and :func:`refine_vertices` slides the
remaining corners towards their neighbours' chord, which brings a path within a fraction of a
percent of the continuous optimum in its homotopy class.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from planner.cspace import CSpace
from semmap.errors import PlanningError
from semmap.grid import Bounds

_OFFSETS = np.array(
    [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)], dtype=np.int64
)
_STEP = np.hypot(_OFFSETS[:, 0], _OFFSETS[:, 1])


@functools.lru_cache(maxsize=4)
def _structure(rows: int, cols: int) -> tuple[NDArray[np.int32], NDArray[np.int32], NDArray[np.bool_]]:
    """Neighbour indices (rows*cols, 8) (self where outside), CSR indptr, and an outside mask.

    int32 indices: SciPy's csgraph works on int32 and would convert int64 on every search.
    """
    n = rows * cols
    if 8 * n >= 2**31:
        raise PlanningError(f"grid of {rows} x {cols} nodes is too large for the search graph")
    r, c = np.divmod(np.arange(n, dtype=np.int64), cols)
    nbr = np.empty((n, 8), dtype=np.int32)
    outside = np.zeros((n, 8), dtype=bool)
    for k, (dr, dc) in enumerate(_OFFSETS):
        r2, c2 = r + dr, c + dc
        ok = (r2 >= 0) & (r2 < rows) & (c2 >= 0) & (c2 < cols)
        nbr[:, k] = np.where(ok, r2 * cols + c2, np.arange(n))
        outside[:, k] = ~ok
    indptr = np.arange(0, 8 * n + 1, 8, dtype=np.int32)
    for a in (nbr, indptr, outside):
        a.setflags(write=False)
    return nbr, indptr, outside


@dataclass(frozen=True)
class SearchOutcome:
    """A grid path (K, 2) in the map frame, or None with ``reachable`` telling why not."""

    path_xy_m: NDArray[np.float64] | None
    #: Whether the goal's node is reachable from the start's node.
    reachable: bool
    #: Start and goal could not be attached to a free node of this graph.
    attach_failed: bool = False


class GridGraph:
    """8-connected graph over a :class:`CSpace`, coarsened by an integer ``factor``.

    Node ``(i, j)`` stands for the block of fine cells ``[i*f, (i+1)*f) x [j*f, (j+1)*f)``
    and sits at the block's centre; it is free only if all its fine cells are, so the straight
    segment between two adjacent free nodes stays inside free cells.
    """

    def __init__(self, cs: CSpace, cost_weight: float, factor: int = 1) -> None:
        if factor < 1:
            raise ValueError(f"factor must be >= 1 (got {factor})")
        self.factor = factor
        self.cost_weight = float(cost_weight)
        rows, cols = cs.spec.shape_rc
        self.shape = (-(-rows // factor), -(-cols // factor))
        self.step_m = cs.spec.resolution_m * factor
        self._nbr, self._indptr, self._outside = _structure(*self.shape)
        self._weights = np.empty((self.shape[0] * self.shape[1], 8), dtype=np.float64)
        self.node_free = np.zeros(self.shape, dtype=bool)
        self.node_cost = np.ones(self.shape, dtype=np.float32)
        self.cs = cs
        self._refresh(cs, (0, self.shape[0], 0, self.shape[1]))

    # --- building -------------------------------------------------------------------

    def _pooled(self, cs: CSpace, nr: tuple[int, int, int, int]) -> tuple[NDArray[np.bool_], NDArray[np.float32]]:
        f = self.factor
        r0, r1, c0, c1 = nr
        rows, cols = cs.spec.shape_rc
        fr = cs.free[r0 * f:min(rows, r1 * f), c0 * f:min(cols, c1 * f)]
        fc = cs.cost[r0 * f:min(rows, r1 * f), c0 * f:min(cols, c1 * f)]
        if f == 1:
            return np.array(fr, dtype=bool), np.array(fc, dtype=np.float32)
        pr, pc = (r1 - r0) * f - fr.shape[0], (c1 - c0) * f - fr.shape[1]
        fr = np.pad(fr, ((0, pr), (0, pc)), constant_values=False)
        fc = np.pad(fc, ((0, pr), (0, pc)), constant_values=1.0)
        h, w = r1 - r0, c1 - c0
        free: NDArray[np.bool_] = np.asarray(fr.reshape(h, f, w, f).all(axis=(1, 3)), dtype=bool)
        cost: NDArray[np.float32] = np.asarray(fc.reshape(h, f, w, f).max(axis=(1, 3)), dtype=np.float32)
        return free, cost

    def _refresh(self, cs: CSpace, nr: tuple[int, int, int, int]) -> None:
        """Recompute node state in node window ``nr`` and the weights of edges touching it."""
        r0, r1, c0, c1 = nr
        free, cost = self._pooled(cs, nr)
        self.node_free[r0:r1, c0:c1] = free
        self.node_cost[r0:r1, c0:c1] = cost
        # Edges out of the window grown by one node (their targets may have changed).
        R, C = self.shape
        g0, g1, h0, h1 = max(0, r0 - 1), min(R, r1 + 1), max(0, c0 - 1), min(C, c1 + 1)
        idx = (np.arange(g0, g1)[:, None] * C + np.arange(h0, h1)[None, :]).ravel()
        nbr = self._nbr[idx]
        nf = self.node_free.ravel()
        nc = self.node_cost.ravel().astype(np.float64)
        ok = nf[idx][:, None] & nf[nbr] & ~self._outside[idx]
        w = _STEP[None, :] * self.step_m * (1.0 + self.cost_weight * 0.5 * (nc[idx][:, None] + nc[nbr]))
        self._weights[idx] = np.where(ok, w, np.inf)

    def update(self, cs: CSpace, window: Bounds | None) -> None:
        """Follow a changed configuration space; ``window`` (fine cells) is what changed."""
        self.cs = cs
        if window is None:
            return
        f = self.factor
        self._refresh(cs, (window.r0 // f, -(-window.r1 // f), window.c0 // f, -(-window.c1 // f)))

    # --- queries --------------------------------------------------------------------

    def node_xy(self, ij: NDArray[np.integer]) -> NDArray[np.float64]:
        """(N, 2) node (row, col) -> (N, 2) map-frame xy of the block centres."""
        ijf = np.asarray(ij, dtype=np.float64).reshape(-1, 2)
        ox, oy = self.cs.spec.origin_xy_m
        return np.stack(
            [ox + (ijf[:, 1] + 0.5) * self.step_m, oy + (ijf[:, 0] + 0.5) * self.step_m], axis=1
        )

    def attach(self, xy_m: NDArray[np.floating], max_rings: int = 3) -> int | None:
        """Index of the nearest free node joined to the free point ``xy_m`` by a free segment."""
        xy = np.asarray(xy_m, dtype=np.float64).reshape(2)
        rows, cols = self.shape
        i = int(math.floor((xy[1] - self.cs.spec.origin_xy_m[1]) / self.step_m))
        j = int(math.floor((xy[0] - self.cs.spec.origin_xy_m[0]) / self.step_m))
        if 0 <= i < rows and 0 <= j < cols and self.node_free[i, j]:
            return i * cols + j
        best: tuple[float, int] | None = None
        for ring in range(1, max_rings + 1):
            ii, jj = np.mgrid[i - ring:i + ring + 1, j - ring:j + ring + 1]
            ii, jj = ii.ravel(), jj.ravel()
            ok = (ii >= 0) & (ii < rows) & (jj >= 0) & (jj < cols)
            ii, jj = ii[ok], jj[ok]
            ok = self.node_free[ii, jj]
            ii, jj = ii[ok], jj[ok]
            if len(ii) == 0:
                continue
            centers = self.node_xy(np.stack([ii, jj], axis=1))
            order = np.argsort(np.linalg.norm(centers - xy, axis=1))
            for k in order:
                if self.cs.segment_free(xy, centers[k]):
                    d = float(np.linalg.norm(centers[k] - xy))
                    if best is None or d < best[0]:
                        best = (d, int(ii[k] * cols + jj[k]))
                    break
            if best is not None:
                return best[1]
        return None

    def distances(self, source: int) -> tuple[NDArray[np.float64], NDArray[np.int32]]:
        """Dijkstra from node ``source``: (n,) weighted distances and (n,) predecessors."""
        n = self.shape[0] * self.shape[1]
        graph = csr_matrix((self._weights.ravel(), self._nbr.ravel(), self._indptr), shape=(n, n))
        dist, pred = dijkstra(graph, directed=True, indices=source, return_predecessors=True)
        return dist, pred

    def search(self, start_xy_m: NDArray[np.floating], goal_xy_m: NDArray[np.floating]) -> SearchOutcome:
        """Shortest weighted node path from a free start to a free goal, both in the map frame."""
        s = self.attach(start_xy_m)
        g = self.attach(goal_xy_m)
        if s is None or g is None:
            return SearchOutcome(None, reachable=False, attach_failed=True)
        dist, pred = self.distances(s)
        if not np.isfinite(dist[g]):
            return SearchOutcome(None, reachable=False)
        chain = [g]
        while chain[-1] != s:
            chain.append(int(pred[chain[-1]]))
        chain.reverse()
        ij = np.stack(np.divmod(np.array(chain, dtype=np.int64), self.shape[1]), axis=1)
        pts = self.node_xy(ij)
        start = np.asarray(start_xy_m, dtype=np.float64).reshape(1, 2)
        goal = np.asarray(goal_xy_m, dtype=np.float64).reshape(1, 2)
        path = np.vstack([start, pts, goal])
        return SearchOutcome(_dedupe(path), reachable=True)

    def reachable_nearest(
        self, start_xy_m: NDArray[np.floating], target_xy_m: NDArray[np.floating]
    ) -> NDArray[np.float64] | None:
        """The centre of the reachable node nearest to ``target_xy_m`` (None if none is)."""
        s = self.attach(start_xy_m)
        if s is None:
            return None
        dist, _ = self.distances(s)
        reach = np.flatnonzero(np.isfinite(dist))
        if len(reach) == 0:
            return None
        ij = np.stack(np.divmod(reach, self.shape[1]), axis=1)
        xy = self.node_xy(ij)
        k = int(np.argmin(np.linalg.norm(xy - np.asarray(target_xy_m, dtype=np.float64).reshape(1, 2), axis=1)))
        return xy[k]


def _dedupe(path: NDArray[np.float64]) -> NDArray[np.float64]:
    keep = np.ones(len(path), dtype=bool)
    keep[1:] = np.linalg.norm(np.diff(path, axis=0), axis=1) > 1e-9
    return path[keep]


def _segment_objective(cs: CSpace, a: NDArray[np.float64], b: NDArray[np.float64], w: float) -> float:
    """Objective of a -> b (length + w * cost integral); inf if not free."""
    free, length, integral = cs.segment_eval(a, b)
    return length + w * integral if free else math.inf


def shortcut(cs: CSpace, path_xy_m: NDArray[np.floating], cost_weight: float) -> NDArray[np.float64]:
    """Greedy any-angle shortcutting of a free (K, 2) polyline.

    From each kept vertex, jump to the farthest later vertex whose straight segment is free
    and whose objective (length + weight * cost integral) is not worse than the part of the
    path it replaces (exponential then binary search over the vertex index).
    """
    p = np.asarray(path_xy_m, dtype=np.float64).reshape(-1, 2)
    n = len(p)
    if n <= 2:
        return p.copy()
    # Objective of the original (short) segments: trapezoid on the vertices' cell costs.
    c = cs.cost_at(p).astype(np.float64)
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1) * (1.0 + cost_weight * 0.5 * (c[:-1] + c[1:]))
    cum = np.concatenate([[0.0], np.cumsum(seg)])

    def ok(i: int, j: int) -> bool:
        if j == i + 1:
            return True
        return _segment_objective(cs, p[i], p[j], cost_weight) <= cum[j] - cum[i] + 1e-9

    out = [p[0]]
    i = 0
    while i < n - 1:
        lo, step, hi = i + 1, 1, None
        while True:
            j = min(i + 2 * step, n - 1)
            if ok(i, j):
                lo = j
                if j == n - 1:
                    break
                step *= 2
            else:
                hi = j
                break
        if hi is not None:
            while hi - lo > 1:
                mid = (lo + hi) // 2
                if ok(i, mid):
                    lo = mid
                else:
                    hi = mid
        out.append(p[lo])
        i = lo
    return np.array(out)


def refine_vertices(
    cs: CSpace, path_xy_m: NDArray[np.floating], cost_weight: float, rounds: int = 3
) -> NDArray[np.float64]:
    """Slide each interior vertex of a free polyline towards its neighbours' chord.

    For each corner, bisect the largest move towards the chord's closest point (and towards
    the neighbours themselves) that keeps both adjacent segments free and lowers the
    objective; vertices that end up on the chord are dropped. The path stays free.
    """
    p = np.asarray(path_xy_m, dtype=np.float64).reshape(-1, 2).copy()
    for _ in range(rounds):
        moved = False
        k = 1
        while k < len(p) - 1:
            a, v, b = p[k - 1], p[k], p[k + 1]
            base = _segment_objective(cs, a, v, cost_weight) + _segment_objective(cs, v, b, cost_weight)
            if _segment_objective(cs, a, b, cost_weight) <= base + 1e-9:
                p = np.delete(p, k, axis=0)
                moved = True
                continue
            ab = b - a
            t = float(np.clip(np.dot(v - a, ab) / max(float(np.dot(ab, ab)), 1e-12), 0.0, 1.0))
            target = a + t * ab
            best_v, best_cost = v, base
            lo, hi = 0.0, 1.0
            for _ in range(5):
                mid = 0.5 * (lo + hi)
                cand = v + mid * (target - v)
                c = _segment_objective(cs, a, cand, cost_weight) + _segment_objective(cs, cand, b, cost_weight)
                if math.isfinite(c):
                    if c < best_cost - 1e-9:
                        best_v, best_cost = cand, c
                    lo = mid
                else:
                    hi = mid
            if best_v is not v and float(np.linalg.norm(best_v - v)) > 1e-4:
                p[k] = best_v
                moved = True
            k += 1
        if not moved:
            break
    return p
