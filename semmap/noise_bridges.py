"""Cut the chains of noisy points that join two objects in one cluster.

Far from the camera the clustering distance grows with the pixel spacing (a table top seen at a
grazing angle must stay one cluster, see :mod:`semmap.geometry`), and so does the depth noise:
at 4 m a D455 point is off by about 8 cm along its ray. A coffee table 0.3 m in front of a sofa
is then joined to it by single linkage through the few noisy points that fall in the gap. The
surfaces of both stay dense, the gap between them does not: a voxel with many neighbours within
the clustering distance (a *core* voxel, as DBSCAN names it) lies on a surface, and only chains
of core voxels join. The other voxels go with the nearest core voxel within the distance, or
with none.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from semmap.clustering import euclidean_clusters

__all__ = ["CORE_FRAC", "dense_parts"]

#: A voxel is on a surface (a core voxel) when the cells around it hold at least this share of
#: what the median voxel's do; points in a gap have far fewer neighbours.
CORE_FRAC = 0.5
#: Cells of the neighbour count at most; a larger cluster is counted on coarser cells.
_MAX_CELLS = 2_000_000


def dense_parts(voxels_m: NDArray[np.float64], distance_m: float, core_frac: float = CORE_FRAC) -> NDArray[np.int64]:
    """(M,) part label of a cluster's voxels (M, 3): parts are joined only by chains of core
    voxels (see the module doc) at most ``distance_m`` apart, ordered by size (0 the largest).
    A voxel's neighbours are those in the 3 x 3 x 3 cells of side ``distance_m / 2`` around it
    (a cube about as large as the ball of radius ``distance_m``); a voxel that is not core goes
    with the nearest core voxel within ``distance_m``, else with none (-1)."""
    vox = np.asarray(voxels_m, dtype=np.float64).reshape(-1, 3)
    if distance_m <= 0.0:
        raise ValueError(f"distance_m must be > 0 (got {distance_m})")
    labels = np.full(len(vox), -1, dtype=np.int64)
    if len(vox) == 0:
        return labels
    extent = np.ptp(vox, axis=0) + distance_m
    cell = max(distance_m / 2.0, (float(np.prod(extent)) / _MAX_CELLS) ** (1.0 / 3.0))
    ijk = np.floor((vox - vox.min(axis=0)) / cell).astype(np.int64) + 1  # a cell of margin on each side
    dims = tuple(int(d) for d in ijk.max(axis=0) + 2)
    flat = np.ravel_multi_index((ijk[:, 0], ijk[:, 1], ijk[:, 2]), dims)
    grid = np.bincount(flat, minlength=int(np.prod(dims))).reshape(dims)
    for axis in range(3):  # the 3 x 3 x 3 block sum, one axis at a time
        g = np.moveaxis(grid, axis, 0)
        block = np.zeros_like(g)
        block[1:-1] = g[:-2] + g[1:-1] + g[2:]
        grid = np.moveaxis(block, 0, axis)
    neighbours = grid.reshape(-1)[flat]
    core = neighbours >= core_frac * float(np.median(neighbours))
    labels[core] = euclidean_clusters(vox[core], distance_m)
    rest = np.flatnonzero(~core)
    if len(rest):
        dist, nearest = cKDTree(vox[core]).query(vox[rest], distance_upper_bound=distance_m)
        reached = np.isfinite(dist)
        labels[rest[reached]] = labels[np.flatnonzero(core)[nearest[reached]]]
    return labels
