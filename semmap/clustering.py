"""Voxel downsampling and Euclidean clustering of point clouds, vectorised.

Clustering is voxel connectivity: space is cut into cubic cells of side ``distance_m`` and two
points belong to the same cluster when a chain of occupied cells, each touching the next in the
26-neighbourhood, joins them. This is single-linkage clustering with the grid doing the
neighbour search, slightly coarser than exact Euclidean clustering at ``distance_m``: two points
closer than ``distance_m`` always share a cluster, points of different clusters are always more
than ``distance_m`` apart (their cells do not touch), and one link of a chain may span up to
2*sqrt(3)*``distance_m`` (opposite corners of touching cells).

Each axis is compressed before labelling: every run of empty cell slices along an axis (the gap
between an object and the wall far behind it, a stray far point) becomes a single empty slice.
Whether two cells touch depends only on whether their indices differ by at most one along each
axis, which this preserves exactly, so the labels are those of the uncompressed grid, at a cost
that follows the occupied extent rather than the bounding box. The occupied cells of the
compressed grid are then joined by a union-find over their 13 raster-earlier neighbours,
compiled with numba (:func:`_grid_labels`, the whole step in one call: a few hundred cells per
object, where numpy's per-call cost would dominate); components are numbered in raster order
of their first cell, as ``scipy.ndimage.label`` numbers them. A cloud whose compressed grid is
still large keeps its cells sparse (sorted keys, ``searchsorted``, a scipy sparse graph), with
the same labels. Several times faster than a k-d tree radius search followed by connected
components on the few thousand points of one object.

numba compiles the kernels on first use and caches them (``cache=True``): in ``__pycache__``
beside this module, or, where that is read-only, in numba's per-user cache directory
(``~/.cache/numba``), or in ``$NUMBA_CACHE_DIR`` when set. A cold compile takes about a second;
a cached load a tenth of that.

Per-axis work runs on (3, N) coordinate rows: reductions over the points of one axis are then
contiguous, where on (N, 3) they stride.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

#: The 13 "forward" offsets of the 26-neighbourhood (the other 13 are their negatives).
_HALF_NEIGHBOURS = np.array(
    [
        (di, dj, dk)
        for di in (-1, 0, 1)
        for dj in (-1, 0, 1)
        for dk in (-1, 0, 1)
        if (di, dj, dk) > (0, 0, 0)
    ],
    dtype=np.int64,
)  # (13, 3)


#: Above this many cells in the compressed grid (its cell index table), components are found
#: sparsely.
_DENSE_MAX_CELLS = 300_000
#: A voxel key range up to this many cells per point is counted densely (no sort).
_COMPACT_CELLS_PER_POINT = 4


def _cell_indices(points_m: NDArray[np.floating], cell_m: float) -> NDArray[np.int64]:
    """(3, N) int64 cell indices of (N, 3) points, shifted so each axis starts at 0."""
    pts_t = np.ascontiguousarray(np.asarray(points_m, dtype=np.float64).reshape(-1, 3).T)  # (3, N)
    ijk = np.floor(pts_t / cell_m).astype(np.int64)
    ijk -= ijk.min(axis=1, keepdims=True)
    return ijk


def _compress_axes(ijk: NDArray[np.int64]) -> NDArray[np.int64]:
    """Renumber the (3, N) non-negative cell indices of each axis, preserving order: a run of
    unoccupied indices between two occupied ones becomes exactly one unoccupied index, so
    "differ by at most one" (touching cells) is preserved exactly."""
    span = ijk.max(axis=1) + 2  # one unoccupied slot after each axis: no leak between axes
    start = np.concatenate([[0], np.cumsum(span)[:-1]])  # (3,)
    flat = ijk + start[:, None]
    occ = np.zeros(int(span.sum()), dtype=bool)
    occ[flat] = True
    occ[1:] |= occ[:-1].copy()  # also keep the first empty slot after each occupied run
    new = np.cumsum(occ)
    out = new[flat]
    out -= new[start][:, None]
    out -= out.min(axis=1, keepdims=True)
    return out


def _keys(ijk: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Row-major int64 key (N,) of (3, N) non-negative cell indices, and the span (3,)."""
    span = ijk.max(axis=1) + 1
    return (ijk[0] * span[1] + ijk[1]) * span[2] + ijk[2], span


def voxel_downsample(
    points_m: NDArray[np.floating], voxel_m: float
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Replace the points of each occupied voxel by their mean (Open3D's ``voxel_down_sample``).

    ``points_m``: (N, 3) in any metric frame. Returns ``(centroids (M, 3) float64,
    inverse (N,) int64)`` where ``inverse[i]`` is the voxel (row of ``centroids``) of point i.
    Voxels come in row-major order of their (x, y, z) cell indices.
    """
    if voxel_m <= 0.0:
        raise ValueError(f"voxel_m must be > 0 (got {voxel_m})")
    pts_t = np.ascontiguousarray(np.asarray(points_m, dtype=np.float64).reshape(-1, 3).T)  # (3, N)
    n = pts_t.shape[1]
    if n == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    ijk = np.floor(pts_t / voxel_m).astype(np.int64)
    ijk -= ijk.min(axis=1, keepdims=True)
    keys, span = _keys(ijk)
    n_cells = int(span[0] * span[1] * span[2])
    # (Compressing the axes first rarely helps here: 3 cm voxels over a whole object are
    # dozens of cells per point even without gaps, and np.unique's sort is then cheaper.)
    if n_cells <= _COMPACT_CELLS_PER_POINT * n:
        # Compact key range: count per cell and renumber occupied cells, no sort needed.
        per_cell = np.bincount(keys, minlength=n_cells)
        occupied = per_cell > 0
        inverse = (np.cumsum(occupied) - 1)[keys]
        counts = per_cell[occupied]
    else:
        _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
        inverse = inverse.reshape(-1)
    m = len(counts)
    sums = np.stack([np.bincount(inverse, weights=pts_t[a], minlength=m) for a in range(3)], 1)
    return sums / counts[:, None], inverse


def euclidean_clusters(
    points_m: NDArray[np.floating], distance_m: float, min_points: int = 1
) -> NDArray[np.int64]:
    """Cluster label per point by voxel connectivity at ``distance_m`` (see the module doc).

    ``points_m``: (N, 3). Returns (N,) int64 labels ordered by size: 0 is the largest cluster,
    1 the next, ... (ties: the cluster whose first cell comes first in row-major (x, y, z)
    order); clusters with fewer than ``min_points`` points get -1.
    """
    if distance_m <= 0.0:
        raise ValueError(f"distance_m must be > 0 (got {distance_m})")
    pts_t = np.ascontiguousarray(np.asarray(points_m, dtype=np.float64).reshape(-1, 3).T)  # (3, N)
    n = pts_t.shape[1]
    if n == 0:
        return np.zeros(0, np.int64)
    point_label = _grid_labels(pts_t, float(distance_m), _DENSE_MAX_CELLS)
    if len(point_label) != n:
        # The compressed grid is too large for a cell index table: sparse cells, with one
        # cell of slack on each side so every neighbour's key is distinct and >= 0.
        ijk = _compress_axes(_cell_indices(pts_t.T, distance_m))
        span = ijk.max(axis=1) + 3
        padded = ijk + 1
        point_label = _sparse_labels((padded[0] * span[1] + padded[1]) * span[2] + padded[2], span)
    sizes = np.bincount(point_label)
    order = np.argsort(-sizes, kind="stable")  # label ids by decreasing size
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    out = rank[point_label]
    if min_points > 1:
        out[sizes[point_label] < min_points] = -1
    return out


@numba.njit(cache=True)
def _find(parent: NDArray[np.int64], x: int) -> int:
    """Root of ``x`` in a union-find forest, compressing the path."""
    root = x
    while parent[root] != root:
        root = parent[root]
    while parent[x] != root:
        nxt = parent[x]
        parent[x] = root
        x = nxt
    return root


@numba.njit(cache=True)
def _grid_labels(pts_t: NDArray[np.float64], cell_m: float, max_cells: int) -> NDArray[np.int64]:
    """Component label (N,) of each point of ``pts_t`` (3, N) under 26-connectivity of cells
    of side ``cell_m``, numbered in raster (x, y, z) order of each component's first cell.

    The same cells, compression and numbering as :func:`_compress_axes` followed by
    ``ndimage.label``; returns an empty array when the compressed grid has more than
    ``max_cells`` cells (the caller then labels sparsely).
    """
    n = pts_t.shape[1]
    ijk = np.empty((3, n), np.int64)
    span = np.empty(3, np.int64)
    for a in range(3):
        lo = np.iinfo(np.int64).max
        hi = np.iinfo(np.int64).min
        for p in range(n):
            v = int(math.floor(pts_t[a, p] / cell_m))
            ijk[a, p] = v
            if v < lo:
                lo = v
            if v > hi:
                hi = v
        # Gap compression: keep each occupied index and the first empty one after a run.
        occ = np.zeros(hi - lo + 2, np.bool_)
        for p in range(n):
            occ[ijk[a, p] - lo] = True
        new = np.empty(hi - lo + 2, np.int64)
        c = -1
        prev = False
        for i in range(hi - lo + 2):
            if occ[i] or prev:
                c += 1
            new[i] = c
            prev = occ[i]
        top = 0
        for p in range(n):
            v = new[ijk[a, p] - lo]
            ijk[a, p] = v
            if v > top:
                top = v
        span[a] = top + 1
    s1, s2 = span[1], span[2]
    n_cells = span[0] * s1 * s2
    if n_cells > max_cells:
        return np.empty(0, np.int64)
    # Occupied cells numbered in raster order: grid holds each cell's number, -1 if empty.
    grid = np.full(n_cells, -1, np.int64)
    keys = np.empty(n, np.int64)
    for p in range(n):
        k = (ijk[0, p] * s1 + ijk[1, p]) * s2 + ijk[2, p]
        keys[p] = k
        grid[k] = 0
    m = 0
    for k in range(n_cells):
        if grid[k] == 0:
            grid[k] = m
            m += 1
    cell_key = np.empty(m, np.int64)
    for k in range(n_cells):
        if grid[k] >= 0:
            cell_key[grid[k]] = k
    # Union with the 13 raster-earlier neighbours; the root is the earliest cell.
    parent = np.arange(m)
    for g in range(m):
        k = cell_key[g]
        i, j, kk0 = k // (s1 * s2), (k // s2) % s1, k % s2
        for di in range(-1, 1):
            ii = i + di
            if ii < 0:
                continue
            for dj in range(-1, 2):
                jj = j + dj
                if jj < 0 or jj >= s1:
                    continue
                for dk in range(-1, 2):
                    if di == 0 and (dj > 0 or (dj == 0 and dk >= 0)):
                        continue
                    kk = kk0 + dk
                    if kk < 0 or kk >= s2:
                        continue
                    h = grid[(ii * s1 + jj) * s2 + kk]
                    if h >= 0:
                        ra, rb = _find(parent, g), _find(parent, h)
                        if ra < rb:
                            parent[rb] = ra
                        elif rb < ra:
                            parent[ra] = rb
    comp = np.full(m, -1, np.int64)
    n_comp = 0
    for g in range(m):
        r = _find(parent, g)
        if comp[r] < 0:
            comp[r] = n_comp
            n_comp += 1
        comp[g] = comp[r]
    out = np.empty(n, np.int64)
    for p in range(n):
        out[p] = comp[grid[keys[p]]]
    return out


def _sparse_labels(keys: NDArray[np.int64], span: NDArray[np.int64]) -> NDArray[np.int64]:
    """Connected components of occupied cells kept sparse (sorted keys, ``searchsorted``), for
    clouds whose grid would be too large even compressed. ``keys``: (N,) row-major keys with
    at least one cell of slack on each side in the layout ``span`` (3,). Returns a label per
    point, numbered in key order of the components' first cells (as ``ndimage.label``)."""
    # Key differences of the 13 forward neighbour cells in this key layout.
    offsets = (_HALF_NEIGHBOURS[:, 0] * span[1] + _HALF_NEIGHBOURS[:, 1]) * span[2] + _HALF_NEIGHBOURS[:, 2]
    cells, inverse = np.unique(keys, return_inverse=True)
    inverse = inverse.reshape(-1)
    m = len(cells)
    target = (cells[:, None] + offsets[None, :]).reshape(-1)  # (M * 13,)
    pos = np.minimum(np.searchsorted(cells, target), m - 1)
    hit = cells[pos] == target
    r = np.nonzero(hit)[0] // len(offsets)
    c = pos[hit]
    # Rows come out sorted (row-major scan), so CSR is built directly without a COO detour.
    indptr = np.concatenate([[0], np.cumsum(np.bincount(r, minlength=m))])
    graph = csr_matrix((np.ones(len(r), np.int8), c, indptr), shape=(m, m))
    _, cell_label = connected_components(graph, directed=False)
    return np.asarray(cell_label[inverse], dtype=np.int64)


def largest_cluster(
    points_m: NDArray[np.floating], distance_m: float, min_points: int = 1
) -> NDArray[np.int64]:
    """Indices (K,) of the points of the largest cluster; empty when no cluster has
    ``min_points`` points. ``points_m``: (N, 3)."""
    labels = euclidean_clusters(points_m, distance_m, min_points)
    return np.nonzero(labels == 0)[0]
