"""Voxel downsampling and Euclidean clustering of point clouds, vectorised.

Clustering is exact single linkage at ``distance_m`` (Euclidean clustering as the reference
design and PCL mean it, and what Open3D's ``cluster_dbscan(eps, min_points=1)`` computes): two
points share a cluster exactly when a chain of points joins them in which each link is at most
``distance_m`` long. Points of different clusters are therefore always more than
``distance_m`` apart, however close their voxels or grid cells are.

The neighbour search is a grid of cubic cells of side ``distance_m / sqrt(3)`` (a hair less):
any two points of one cell are within ``distance_m`` (the cell's diagonal), so a cell is a
clique and the union-find runs over cells, not points. Points within ``distance_m`` of a
cell's points lie in cells at most two apart along every axis; each cell looks at the
raster-later ones of those (the others look at it), skips those already in its component,
and joins the rest when some pair of points is within ``distance_m`` (squared distances, no
square root; the scan stops at the first such pair). Each axis of the grid is compressed
first: every run of more than two empty cell slices along an axis (the gap between an object
and the wall far behind it, a stray far point) becomes two, which keeps "differ by at most
two indices" exactly, so the tables follow the occupied extent rather than the bounding box.
Points are bucketed by cell with counting sorts (z index, then the (x, y) column of cells);
cells are visited in key order, so the candidates in each of the 13 neighbour columns (found
through a table over the columns) are reached by a pointer that only moves forward. A cloud
whose compressed grid has too many columns for such a table (over
``_DENSE_CELLS_PER_POINT`` per point) sorts its keys and hashes its columns instead, with
the same labels. Components are numbered in raster (x, y, z) order of their first cell. The
whole step is one numba call (:func:`_linkage_labels`): a few hundred to a few thousand
voxels per object, where numpy's per-call cost would dominate. (Voxel connectivity - cells
of side ``distance_m`` joined when they touch - is several times cheaper but links points up
to 2*sqrt(3)*``distance_m`` apart: an object and the wall or neighbour 6-15 cm behind it
became one cluster.)

numba compiles the kernels on first use and caches them (``cache=True``): in ``__pycache__``
beside this module, or, where that is read-only, in numba's per-user cache directory
(``~/.cache/numba``), or in ``$NUMBA_CACHE_DIR`` when set. A cold compile takes about a second;
a cached load a tenth of that (:func:`semmap.kernels.warm_up` pays it at start).

Per-axis work runs on (3, N) coordinate rows: reductions over the points of one axis are then
contiguous, where on (N, 3) they stride.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray

#: Up to this many (x, y) columns of cells per point (plus a few thousand) in the compressed
#: grid, points are bucketed by counting sorts and columns found through a table; beyond it
#: by a merge sort and a hash table.
_DENSE_CELLS_PER_POINT = 32
#: A voxel key range up to this many cells per point is counted densely (no sort).
_COMPACT_CELLS_PER_POINT = 4


def _keys(ijk: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Row-major int64 key (N,) of (3, N) non-negative cell indices, and the span (3,)."""
    span = ijk.max(axis=1) + 1
    return (ijk[0] * span[1] + ijk[1]) * span[2] + ijk[2], span


def voxel_downsample(
    points_m: NDArray[np.floating], voxel_m: float
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Replace the points of each occupied voxel by their mean (Open3D's ``voxel_down_sample``).

    ``points_m``: (N, 3) in any metric frame. Voxels are the cells
    ``floor(p / voxel_m)``: the grid is anchored at the frame's origin (Open3D's
    ``voxel_down_sample`` anchors it at the cloud's minimum less half a voxel;
    ``voxel_down_sample_and_trace`` with a ``min_bound`` on multiples of ``voxel_m`` gives
    these voxels). Returns ``(centroids (M, 3) float64, inverse (N,) int64)`` where
    ``inverse[i]`` is the voxel (row of ``centroids``) of point i. Voxels come in row-major
    order of their (x, y, z) cell indices.
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
    """Cluster label per point by exact single linkage at ``distance_m`` (see the module doc):
    points at most ``distance_m`` apart share a cluster, and so do chains of such links.

    ``points_m``: (N, 3), metres (any frame). Returns (N,) int64 labels ordered by size: 0 is
    the largest cluster, 1 the next, ... (ties: the cluster whose first cell of side
    ``distance_m`` comes first in row-major (x, y, z) order); clusters with fewer than
    ``min_points`` points get -1.
    """
    if distance_m <= 0.0:
        raise ValueError(f"distance_m must be > 0 (got {distance_m})")
    pts_t = np.ascontiguousarray(np.asarray(points_m, dtype=np.float64).reshape(-1, 3).T)  # (3, N)
    n = pts_t.shape[1]
    if n == 0:
        return np.zeros(0, np.int64)
    if not np.isfinite(pts_t).all():
        raise ValueError("points_m must be finite")
    point_label = _linkage_labels(pts_t, float(distance_m), _DENSE_CELLS_PER_POINT, _COLUMNS)
    if len(point_label) != n:
        raise ValueError(f"{n} points span too many cells of {distance_m} m to be keyed in int64")
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


#: Cells are cubes of side distance / sqrt(3), a hair less, so any two points of one cell are
#: within the distance (a cell's diagonal) whatever the rounding of the cell index.
_CELL_SHRINK = 1.0 - 1e-9


def _forward_columns() -> NDArray[np.int64]:
    """The raster-later neighbour cells within two cells on every axis, as 13 rows
    (di, dj, first dk) of (di, dj) columns searched for dk from the first to 2: every such
    cell can hold points within the distance of a cell's points (the nearest points of cells
    two apart on every axis are just over a cell's diagonal apart)."""
    rows = [(0, 0, 1)] + [(0, 1, -2), (0, 2, -2)] + [(di, dj, -2) for di in (1, 2) for dj in range(-2, 3)]
    return np.array(rows, dtype=np.int64)


_COLUMNS = _forward_columns()  # (13, 3)


@numba.njit(cache=True)
def _hash_slot(key: int, mask: int) -> int:
    """Home slot of a key >= 0 in a table of ``mask + 1`` (a power of two) slots: the key's
    bits mixed (splitmix64's finaliser) so keys that differ only in high bits spread too."""
    h = np.uint64(key)
    h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    h = h ^ (h >> np.uint64(31))
    return int(np.int64(h & np.uint64(mask)))


@numba.njit(cache=True)
def _hash_put(table_key: NDArray[np.int64], table_val: NDArray[np.int64], key: int, val: int) -> None:
    """Insert ``key`` (>= 0, new) -> ``val`` into an open-addressing table (size a power of
    two, empty slots -1) with linear probing."""
    mask = table_key.shape[0] - 1
    h = _hash_slot(key, mask)
    while table_key[h] >= 0:
        h = (h + 1) & mask
    table_key[h] = key
    table_val[h] = val


@numba.njit(cache=True)
def _hash_get(table_key: NDArray[np.int64], table_val: NDArray[np.int64], key: int) -> int:
    """The value of ``key`` in the table of :func:`_hash_put`, -1 when absent."""
    mask = table_key.shape[0] - 1
    h = _hash_slot(key, mask)
    while table_key[h] >= 0:
        if table_key[h] == key:
            return int(table_val[h])
        h = (h + 1) & mask
    return -1


@numba.njit(cache=True)
def _compressed_cells(
    pts_t: NDArray[np.float64], cell_m: float, keep_empty: int
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(3, N) cell indices of side ``cell_m`` of the points ``pts_t`` (3, N), each axis
    gap-compressed - every run of unoccupied indices longer than ``keep_empty`` becomes
    ``keep_empty`` long, order kept, so index differences up to ``keep_empty + 1`` are
    unchanged and larger ones stay larger - and starting at 0; and the span (3,)."""
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
        if hi - lo + 1 > 8 * n + 1024:
            # Sparse along this axis (a stray far point): walk the sorted indices instead of
            # a table over the whole range.
            order = np.argsort(ijk[a])
            c = 0
            prev = ijk[a, order[0]]
            for r in range(n):
                p = order[r]
                v = ijk[a, p]
                c += min(v - prev, keep_empty + 1)
                prev = v
                ijk[a, p] = c
            span[a] = c + 1
            continue
        occ = np.zeros(hi - lo + 1, np.bool_)
        for p in range(n):
            occ[ijk[a, p] - lo] = True
        new = np.empty(hi - lo + 1, np.int64)
        c = -1
        run = 0
        for i in range(hi - lo + 1):
            if occ[i]:
                run = 0
                c += 1
            else:
                run += 1
                if run <= keep_empty:
                    c += 1
            new[i] = c
        top = 0
        for p in range(n):
            v = new[ijk[a, p] - lo]
            ijk[a, p] = v
            if v > top:
                top = v
        span[a] = top + 1
    return ijk, span


@numba.njit(cache=True)
def _linkage_labels(
    pts_t: NDArray[np.float64], eps_m: float, max_cells_per_point: int, columns: NDArray[np.int64]
) -> NDArray[np.int64]:
    """Single-linkage component (N,) of each point of ``pts_t`` (3, N) at ``eps_m``, numbered
    in raster (x, y, z) order of each component's first cell.

    Cells have side ``eps_m / sqrt(3)`` (shrunk by ``_CELL_SHRINK``), so each is a clique;
    the union-find runs over cells (:func:`_link_cells`). Points are sorted by cell key with
    counting sorts and columns found through a table when the compressed grid has at most
    ``max_cells_per_point`` columns per point (plus a few thousand), else by a merge sort
    and a hash of the occupied columns. Returns an empty array when the cell keys would
    overflow int64.
    """
    n = pts_t.shape[1]
    cell_m = eps_m / math.sqrt(3.0) * _CELL_SHRINK
    ijk, span = _compressed_cells(pts_t, cell_m, 2)
    s0, s1, s2 = span[0], span[1], span[2]
    if float(s0) * float(s1) * float(s2) >= 4.0e18:
        return np.empty(0, np.int64)
    n_cols = s0 * s1
    dense = n_cols <= max_cells_per_point * n + 4096
    order = _cell_order(ijk, s1, s2, n_cols, dense)
    cell_start, cell_col, cell_k, x, y, z, m = _cells_in_order(pts_t, ijk, order, s1)
    col_start, col_table, hash_key, hash_val = _column_index(cell_col, m, n_cols, dense)
    parent = _link_cells(cell_start, cell_col, cell_k, x, y, z, m, s0, s1, columns, eps_m * eps_m,
                         col_start, col_table, hash_key, hash_val, dense)
    return _component_labels(parent, cell_start, order, m)


@numba.njit(cache=True)
def _cell_order(
    ijk: NDArray[np.int64], s1: int, s2: int, n_cols: int, dense: bool
) -> NDArray[np.int64]:
    """The point indices sorted (stably) by cell key: two counting sorts (z index, then the
    (x, y) column) when ``dense``, else a merge sort of the keys."""
    n = ijk.shape[1]
    if not dense:
        keys = np.empty(n, np.int64)
        for p in range(n):
            keys[p] = (ijk[0, p] * s1 + ijk[1, p]) * s2 + ijk[2, p]
        return np.argsort(keys, kind="mergesort")
    cnt = np.zeros(s2 + 1, np.int64)
    for p in range(n):
        cnt[ijk[2, p] + 1] += 1
    for k in range(s2):
        cnt[k + 1] += cnt[k]
    by_k = np.empty(n, np.int64)
    for p in range(n):
        by_k[cnt[ijk[2, p]]] = p
        cnt[ijk[2, p]] += 1
    cnt2 = np.zeros(n_cols + 1, np.int64)
    for p in range(n):
        cnt2[ijk[0, p] * s1 + ijk[1, p] + 1] += 1
    for q in range(n_cols):
        cnt2[q + 1] += cnt2[q]
    order = np.empty(n, np.int64)
    for r in range(n):
        p = by_k[r]
        q = ijk[0, p] * s1 + ijk[1, p]
        order[cnt2[q]] = p
        cnt2[q] += 1
    return order


@numba.njit(cache=True)
def _cells_in_order(
    pts_t: NDArray[np.float64], ijk: NDArray[np.int64], order: NDArray[np.int64], s1: int
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64],
           NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], int]:
    """The cells as runs of equal (column, z index) in ``order``, in key order: cell c holds
    the points order[cell_start[c]:cell_start[c + 1]] and lies in column cell_col[c] at z
    index cell_k[c]. Returns those three, the coordinates x, y, z copied in that order (so a
    cell's are contiguous) and the number of cells m."""
    n = order.shape[0]
    cell_start = np.empty(n + 1, np.int64)
    cell_col = np.empty(n, np.int64)
    cell_k = np.empty(n, np.int64)
    x = np.empty(n)
    y = np.empty(n)
    z = np.empty(n)
    m = 0
    last_col, last_k = -1, -1
    for r in range(n):
        p = order[r]
        q, k = ijk[0, p] * s1 + ijk[1, p], ijk[2, p]
        if q != last_col or k != last_k:
            cell_start[m] = r
            cell_col[m] = q
            cell_k[m] = k
            m += 1
            last_col, last_k = q, k
        x[r], y[r], z[r] = pts_t[0, p], pts_t[1, p], pts_t[2, p]
    cell_start[m] = n
    return cell_start, cell_col, cell_k, x, y, z, m


@numba.njit(cache=True)
def _column_index(
    cell_col: NDArray[np.int64], m: int, n_cols: int, dense: bool
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Each occupied column's cells, contiguous and by z index: cells col_start[u] to
    col_start[u + 1] of column number u, found by a table over the columns when ``dense``,
    else by a hash. Returns (col_start, col_table, hash_key, hash_val)."""
    col_start = np.empty(m + 1, np.int64)
    col_table = np.full(n_cols if dense else 0, -1, np.int64)
    size = 1
    while size < 2 * m:
        size *= 2
    hash_key = np.full(0 if dense else size, -1, np.int64)
    hash_val = np.empty(0 if dense else size, np.int64)
    n_u = 0
    for c in range(m):
        if c == 0 or cell_col[c] != cell_col[c - 1]:
            col_start[n_u] = c
            if dense:
                col_table[cell_col[c]] = n_u
            else:
                _hash_put(hash_key, hash_val, cell_col[c], n_u)
            n_u += 1
    col_start[n_u] = m
    return col_start, col_table, hash_key, hash_val


@numba.njit(cache=True)
def _link_cells(
    cell_start: NDArray[np.int64], cell_col: NDArray[np.int64], cell_k: NDArray[np.int64],
    x: NDArray[np.float64], y: NDArray[np.float64], z: NDArray[np.float64], m: int, s0: int, s1: int,
    columns: NDArray[np.int64], eps2: float, col_start: NDArray[np.int64], col_table: NDArray[np.int64],
    hash_key: NDArray[np.int64], hash_val: NDArray[np.int64], dense: bool,
) -> NDArray[np.int64]:
    """Union-find forest (m,) over the cells: two cells at most two apart on every axis (the
    raster-later ones: ``columns`` (13, 3) holds the forward (di, dj) columns and the first
    dk searched in each) join when any pair of their points is within sqrt(``eps2``) -
    checked only while they are still apart. A root is its component's first cell."""
    parent = np.arange(m)
    n_col = columns.shape[0]
    # Per neighbour column: the next candidate cell and the column's end. Within one column
    # the cells come by increasing z index, so each pointer only moves forward.
    ptr = np.zeros(n_col, np.int64)
    pend = np.zeros(n_col, np.int64)
    cur_q = -1
    for c in range(m):
        q, k0 = cell_col[c], cell_k[c]
        if q != cur_q:
            cur_q = q
            _neighbour_columns(q, s0, s1, columns, col_start, col_table, hash_key, hash_val, dense, ptr, pend)
        rc = _find(parent, c)  # kept current below: only this loop's unions move it
        for o in range(n_col):
            # The column's cells with z index in [k0 + first dk, k0 + 2].
            h, end = ptr[o], pend[o]
            k_lo = k0 + columns[o, 2]
            while h < end and cell_k[h] < k_lo:
                h += 1
            ptr[o] = h
            while h < end and cell_k[h] <= k0 + 2:
                rh = _find(parent, h)
                if rc != rh and _cells_within(cell_start, x, y, z, c, h, eps2):
                    if rc < rh:
                        parent[rh] = rc
                    else:
                        parent[rc] = rh
                        rc = rh
                h += 1
    return parent


@numba.njit(cache=True)
def _neighbour_columns(
    q: int, s0: int, s1: int, columns: NDArray[np.int64], col_start: NDArray[np.int64],
    col_table: NDArray[np.int64], hash_key: NDArray[np.int64], hash_val: NDArray[np.int64], dense: bool,
    ptr: NDArray[np.int64], pend: NDArray[np.int64],
) -> None:
    """Set ``ptr``/``pend`` to the cell range of each forward neighbour column of column
    ``q`` (empty where it is outside the grid or unoccupied)."""
    i, j = q // s1, q % s1
    for o in range(columns.shape[0]):
        ii, jj = i + columns[o, 0], j + columns[o, 1]
        ptr[o], pend[o] = 0, 0
        if ii >= s0 or jj < 0 or jj >= s1:
            continue
        qq = ii * s1 + jj
        u = col_table[qq] if dense else _hash_get(hash_key, hash_val, qq)
        if u >= 0:
            ptr[o], pend[o] = col_start[u], col_start[u + 1]


@numba.njit(cache=True)
def _cells_within(
    cell_start: NDArray[np.int64], x: NDArray[np.float64], y: NDArray[np.float64], z: NDArray[np.float64],
    c: int, h: int, eps2: float,
) -> bool:
    """True when some point of cell ``c`` and some point of cell ``h`` are within
    sqrt(``eps2``); stops at the first such pair."""
    for a in range(cell_start[c], cell_start[c + 1]):
        xa, ya, za = x[a], y[a], z[a]
        for b in range(cell_start[h], cell_start[h + 1]):
            dx, dy, dz = x[b] - xa, y[b] - ya, z[b] - za
            if dx * dx + dy * dy + dz * dz <= eps2:
                return True
    return False


@numba.njit(cache=True)
def _component_labels(
    parent: NDArray[np.int64], cell_start: NDArray[np.int64], order: NDArray[np.int64], m: int
) -> NDArray[np.int64]:
    """Each point's component number, in order of the components' first cells."""
    n = order.shape[0]
    comp = np.full(m, -1, np.int64)
    n_comp = 0
    out = np.empty(n, np.int64)
    for c in range(m):
        root = _find(parent, c)
        if comp[root] < 0:
            comp[root] = n_comp
            n_comp += 1
        for r in range(cell_start[c], cell_start[c + 1]):
            out[order[r]] = comp[root]
    return out


def largest_cluster(
    points_m: NDArray[np.floating], distance_m: float, min_points: int = 1
) -> NDArray[np.int64]:
    """Indices (K,) of the points of the largest cluster; empty when no cluster has
    ``min_points`` points. ``points_m``: (N, 3)."""
    labels = euclidean_clusters(points_m, distance_m, min_points)
    return np.nonzero(labels == 0)[0]
