"""Voxel keys, and which points lie in or beside another point set's voxels."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["in_sorted", "voxel_keys", "within_a_voxel"]


def voxel_keys(points_m: NDArray[np.floating], voxel_m: float, shift_m: float = 0.0) -> NDArray[np.int64]:
    """(N,) one integer per voxel ``floor((p + shift_m) / voxel_m)`` of points (N, 3) (21 bits
    per axis: +-31 km at 3 cm)."""
    ijk = _voxel_ijk(points_m, voxel_m, shift_m) + (1 << 20)
    return (ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2]


def _voxel_ijk(points_m: NDArray[np.floating], voxel_m: float, shift_m: float = 0.0) -> NDArray[np.int64]:
    """(N, 3) voxel indices ``floor((p + shift_m) / voxel_m)`` of points (N, 3)."""
    p = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    return np.floor((p + shift_m) / voxel_m).astype(np.int64)


#: Key differences of the 27 voxels around and including one (see :func:`voxel_keys`).
_NEIGHBOUR_KEY_STEPS = np.array([(i << 42) + (j << 21) + k for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)],
                                dtype=np.int64)


#: Largest grid (cells) over the other points' bounds for :func:`within_a_voxel`'s lookup;
#: beyond it (points spread over a room) a binary search over keys costs less.
_DENSE_NEIGHBOUR_CELLS = 400_000


def within_a_voxel(a_m: NDArray[np.floating], b_m: NDArray[np.floating], voxel_m: float) -> NDArray[np.bool_]:
    """(N,) True where a point of ``a_m`` (N, 3) lies in a voxel of a point of ``b_m`` (M, 3) or
    in one of the 26 around it: exact, for taking other objects' points out of a box."""
    b_ijk = _voxel_ijk(b_m, voxel_m)
    a_ijk = _voxel_ijk(a_m, voxel_m)
    if len(b_ijk) == 0:
        return np.zeros(len(a_ijk), dtype=bool)
    lo, hi = b_ijk.min(axis=0) - 1, b_ijk.max(axis=0) + 1
    shape = hi - lo + 1
    if float(np.prod(shape.astype(np.float64))) > _DENSE_NEIGHBOUR_CELLS:
        # A binary search of each neighbour key among b's sorted keys (np.isin would hash all
        # 27 x M grown keys on every call, ten times slower at a frame's sizes).
        wanted = voxel_keys(a_m, voxel_m)[:, None] - _NEIGHBOUR_KEY_STEPS[None, :]  # (N, 27)
        return np.asarray(in_sorted(wanted, np.sort(voxel_keys(b_m, voxel_m))).any(axis=1), dtype=bool)
    # b's voxels and their 26 neighbours on a small grid over b's bounds, looked up per point.
    grid = np.zeros(tuple(shape.tolist()), dtype=bool)
    rel = b_ijk - lo
    grid[rel[:, 0], rel[:, 1], rel[:, 2]] = True
    for axis in range(3):
        src = grid.copy()
        lower = [slice(None)] * 3
        upper = [slice(None)] * 3
        lower[axis], upper[axis] = slice(None, -1), slice(1, None)
        grid[tuple(upper)] |= src[tuple(lower)]
        grid[tuple(lower)] |= src[tuple(upper)]
    out = np.zeros(len(a_ijk), dtype=bool)
    inside = np.flatnonzero(np.all((a_ijk >= lo) & (a_ijk <= hi), axis=1))
    rel = a_ijk[inside] - lo
    out[inside] = grid[rel[:, 0], rel[:, 1], rel[:, 2]]
    return out


def in_sorted(keys: NDArray[np.int64], sorted_keys: NDArray[np.int64]) -> NDArray[np.bool_]:
    """True where an element of ``keys`` (any shape) is in ``sorted_keys`` (K,), ascending."""
    if len(sorted_keys) == 0:
        return np.zeros(keys.shape, dtype=bool)
    at = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
    return np.asarray(sorted_keys[at] == keys, dtype=bool)
