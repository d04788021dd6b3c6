"""Voxel downsampling and Euclidean clustering of point clouds, vectorised.

Clustering is voxel connectivity: space is cut into cubic cells of side ``distance_m`` and two
points belong to the same cluster when a chain of occupied cells, each touching the next in the
26-neighbourhood, joins them. This is single-linkage clustering with the grid doing the
neighbour search, slightly coarser than exact Euclidean clustering at ``distance_m``: two points
closer than ``distance_m`` always share a cluster, points of different clusters are always more
than ``distance_m`` apart (their cells do not touch), and one link of a chain may span up to
2*sqrt(3)*``distance_m`` (opposite corners of touching cells).

The occupied cells are labelled on a dense occupancy grid with ``scipy.ndimage.label`` (one C
pass). The grid is kept small by compressing each axis before labelling: every run of empty
cell slices along an axis (the gap between an object and the wall far behind it, a stray far
point) becomes a single empty slice. Whether two cells touch depends only on whether their
indices differ by at most one along each axis, which this preserves exactly, so the labels are
those of the uncompressed grid, at a cost that follows the occupied extent rather than the
bounding box. Only a cloud whose compressed grid is still large falls back to sparse cells
(sorted keys, ``searchsorted``, a sparse graph). Several times faster than a k-d tree radius
search followed by connected components on the few thousand points of one object.

Per-axis work runs on (3, N) coordinate rows: reductions over the points of one axis are then
contiguous, where on (N, 3) they stride.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
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


#: 26-connectivity structuring element.
_FULL_3X3X3 = np.ones((3, 3, 3), dtype=bool)
#: Above this many cells in the (compressed) grid, components are found sparsely.
_DENSE_MAX_CELLS = 300_000
#: ... or more than this many cells per point (measured break-even of the two passes).
_DENSE_CELLS_PER_POINT = 25
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


def _cell_keys(
    points_m: NDArray[np.floating], cell_m: float, pad: int = 0
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """One int64 cell key per point (N,) and the key layout's span (3,) in cells; ``pad`` cells
    of slack on each side keep the keys of neighbouring cells distinct and non-negative."""
    ijk = _cell_indices(points_m, cell_m) + pad
    span = ijk.max(axis=1) + 1 + pad  # (3,)
    keys = (ijk[0] * span[1] + ijk[1]) * span[2] + ijk[2]
    return keys, span


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
    pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    n = len(pts)
    if n == 0:
        return np.zeros(0, np.int64)
    ijk = _compress_axes(_cell_indices(pts, distance_m))
    keys, span = _keys(ijk)
    n_cells = int(span[0] * span[1] * span[2])
    # The dense pass costs per cell of the grid, the sparse one per point (with a higher
    # constant): dense only while the grid is not much larger than the cloud.
    if n_cells <= min(_DENSE_MAX_CELLS, _DENSE_CELLS_PER_POINT * n):
        occ = np.zeros(n_cells, dtype=bool)
        occ[keys] = True
        grid, _ = ndimage.label(occ.reshape(tuple(int(v) for v in span)), structure=_FULL_3X3X3)
        point_label = grid.reshape(-1)[keys].astype(np.int64) - 1
    else:
        # One cell of slack on each side keeps every neighbour's key distinct and >= 0.
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
