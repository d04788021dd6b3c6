"""Class shape priors: which points of a box's cluster belong to the object the box shows.

Furniture touches: a chair pushed in under a table, chair backs rising beside a table top, a
table top behind a chair's backrest. Depth alone joins them into one cluster. The class says
what shape to expect (``ClassConfig.shape``):

* ``table``: the top is the highest large horizontal surface of the cluster. Nothing above it
  belongs to the table (chair backs, things on the top), and nothing below it outside the top's
  outline (chairs in front of it, their seats): the legs stand under the top.
* ``seat``: a seat with a back above it. A large, dense horizontal surface above seat height
  is another object's top (the table a chair is pushed under): its points are not the chair's.
* ``free``: no prior.

A horizontal surface is a layer of voxels at one height (3 cm bins over the voxel heights);
"large" means it holds a good share of the cluster and spans a real area. Everything here
works on the cluster's voxels (M, 3) in the map frame and their heights above the floor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray

from semmap.polygons import convex_footprint, min_perimeter_rectangle, polygon_area_m2

__all__ = ["Layer", "horizontal_layers", "shape_mask"]

#: Height bin of the layer search, metres.
LAYER_BIN_M = 0.03
#: A layer holds at least this share of the cluster's largest layer (and ``min_points``).
LAYER_MIN_SHARE = 0.3
#: A table's top spans at least this area (m^2) to be trusted as the top.
TABLE_TOP_MIN_AREA_M2 = 0.08
#: Points this far above the table top still belong to it (noise, a thin cloth).
TABLE_ABOVE_TOP_M = 0.03
#: Points below the top belong to the table within this distance outside the top's outline.
TABLE_OUTLINE_MARGIN_M = 0.10
#: A seat is at most this high: a surface between it and ``FOREIGN_TOP_MAX_HEIGHT_M`` (table
#: heights) in a seat's cluster is another object's top.
SEAT_MAX_HEIGHT_M = 0.6
FOREIGN_TOP_MAX_HEIGHT_M = 0.95
#: Such a foreign top spans at least this area (m^2) and this short side, densely (voxels
#: cover at least ``FOREIGN_TOP_MIN_FILL`` of its hull): a backrest's top edge or an armrest
#: is a strip, and two armrests are a sparse hull.
FOREIGN_TOP_MIN_AREA_M2 = 0.05
FOREIGN_TOP_MIN_SHORT_M = 0.15
FOREIGN_TOP_MIN_FILL = 0.4


@dataclass(frozen=True)
class Layer:
    """A horizontal surface: ``height_m`` above the floor, its voxels ``members`` (M,) bool,
    their convex hull ``hull_xy_m`` (K, 2) and its ``area_m2``, ``fill`` (voxel area over hull
    area) and its rectangle's ``long_side_m`` and ``short_side_m``."""

    height_m: float
    members: NDArray[np.bool_]
    hull_xy_m: NDArray[np.float64]
    area_m2: float
    fill: float
    long_side_m: float
    short_side_m: float


def horizontal_layers(
    xyz_m: NDArray[np.float64], heights_m: NDArray[np.float64], voxel_m: float, min_points: int,
    between_m: tuple[float, float] = (-np.inf, np.inf), highest_only: bool = False, min_area_m2: float = 0.0,
) -> list[Layer]:
    """The horizontal surfaces of a cluster's voxels (M, 3) with heights (M,), lowest first:
    height bins (``LAYER_BIN_M``, two adjacent bins together) holding at least ``min_points``
    voxels and ``LAYER_MIN_SHARE`` of the fullest bin pair; of neighbouring candidates the
    fuller one. Only candidates starting within ``between_m`` are measured; ``highest_only``:
    just the highest surface spanning ``TABLE_TOP_MIN_AREA_M2`` (what a table prior needs).
    ``min_area_m2``: surfaces spanning less are left out (they still hide a candidate next to
    them), so a caller that would reject them anyway does not pay for their rectangles."""
    h = np.asarray(heights_m, dtype=np.float64)
    if len(h) < min_points:
        return []
    lo = float(h.min())
    idx = np.floor((h - lo) / LAYER_BIN_M).astype(np.int64)
    counts = np.bincount(idx)
    pair = counts + np.concatenate([counts[1:], [0]])
    need = max(float(min_points), LAYER_MIN_SHARE * float(pair.max()))
    pc = pair.tolist()  # plain ints: the scan below compares each bin with its neighbours
    cand = [k for k in range(len(pc)) if pc[k] >= need
            and pc[k] >= (pc[k - 1] if k > 0 else 0) and pc[k] >= (pc[k + 1] if k + 1 < len(pc) else 0)
            and between_m[0] < lo + k * LAYER_BIN_M <= between_m[1]]
    if highest_only:
        min_area_m2 = max(min_area_m2, TABLE_TOP_MIN_AREA_M2)  # a smaller highest surface is never returned
    out: list[Layer] = []
    last_height_m: float | None = None  # of the last surface found, also one too small to return
    for k in (cand[::-1] if highest_only else cand):
        if last_height_m is not None and abs(k - int(round((last_height_m - lo) / LAYER_BIN_M))) <= 1:
            continue  # the same surface over two bin pairs
        pair_members = (idx == k) | (idx == k + 1)
        members = np.abs(h - float(np.median(h[pair_members]))) <= LAYER_BIN_M
        solid = _solid_part(xyz_m[members, :2], voxel_m)
        if solid.sum() < min_points:
            continue  # thin structures crossing this height, not a surface
        members[np.flatnonzero(members)[~solid]] = False
        last_height_m = float(np.median(h[members]))
        xy = xyz_m[members, :2]
        hull = convex_footprint(xy, min_width_m=voxel_m)
        area = polygon_area_m2(hull)
        if area < min_area_m2:
            continue
        rect = min_perimeter_rectangle(hull)
        sides = np.hypot(*(rect[1] - rect[0])), np.hypot(*(rect[3] - rect[0]))
        fill = min(1.0, float(members.sum()) * voxel_m * voxel_m / area) if area > 0 else 0.0
        out.append(Layer(last_height_m, members, hull, area, fill, float(max(sides)), float(min(sides))))
        if highest_only:
            return out
    return [] if highest_only else out


def _solid_part(xy_m: NDArray[np.float64], cell_m: float) -> NDArray[np.bool_]:
    """(N,) True for points (N, 2) in the solid part of their map-plane occupancy: cells closed
    then opened with a 3x3 square, so strips two cells wide or less (the slats of a chair back
    crossing a table top's height) drop out and gaps of a sparse sampling do not."""
    ij = np.floor((xy_m - xy_m.min(axis=0)) / cell_m).astype(np.int64) + 2
    size = ij.max(axis=0) + 3
    return np.asarray(_solid_cells(np.ascontiguousarray(ij), int(size[0]), int(size[1])), dtype=bool)


@numba.njit(cache=True)
def _square3(grid: NDArray[np.bool_], dilate: bool) -> NDArray[np.bool_]:
    """Binary dilation (or erosion) of ``grid`` with a 3x3 square, cells outside it False:
    what ``scipy.ndimage`` does with its default border, without its per-call cost. The
    square is separable: a 3-cell pass along each axis."""
    n0, n1 = grid.shape
    rows = np.zeros((n0, n1), np.bool_)
    for i in range(n0):
        for j in range(n1):
            left = grid[i, j - 1] if j > 0 else False
            right = grid[i, j + 1] if j < n1 - 1 else False
            if dilate:
                rows[i, j] = left or grid[i, j] or right
            else:
                rows[i, j] = left and grid[i, j] and right
    out = np.zeros((n0, n1), np.bool_)
    for i in range(n0):
        for j in range(n1):
            up = rows[i - 1, j] if i > 0 else False
            down = rows[i + 1, j] if i < n0 - 1 else False
            if dilate:
                out[i, j] = up or rows[i, j] or down
            else:
                out[i, j] = up and rows[i, j] and down
    return out


@numba.njit(cache=True)
def _solid_cells(ij: NDArray[np.int64], n0: int, n1: int) -> NDArray[np.bool_]:
    """(N,) True for cells ``ij`` (N, 2) of an (n0, n1) grid that are occupied after closing
    then opening the occupancy with a 3x3 square (see :func:`_solid_part`)."""
    occ = np.zeros((n0, n1), np.bool_)
    for p in range(ij.shape[0]):
        occ[ij[p, 0], ij[p, 1]] = True
    closed = _square3(_square3(occ, True), False)
    solid = _square3(_square3(closed, False), True)
    out = np.empty(ij.shape[0], np.bool_)
    for p in range(ij.shape[0]):
        out[p] = solid[ij[p, 0], ij[p, 1]]
    return out


def _near_hull(hull: NDArray[np.float64], xy: NDArray[np.float64], margin_m: float) -> NDArray[np.bool_]:
    """(N,) True where points (N, 2) lie inside the counter-clockwise convex polygon (K, 2) or
    within ``margin_m`` outside each of its edges' lines."""
    if len(hull) < 3:
        return np.ones(len(xy), dtype=bool)
    a, b = hull, np.roll(hull, -1, axis=0)
    e = b - a
    length = np.maximum(np.hypot(e[:, 0], e[:, 1]), 1e-9)
    # Signed distance outside each edge (positive = outside for a counter-clockwise polygon).
    outside = ((xy[:, None, 0] - a[None, :, 0]) * e[None, :, 1] - (xy[:, None, 1] - a[None, :, 1]) * e[None, :, 0])
    return np.all(outside / length[None, :] <= margin_m, axis=1)


def shape_mask(
    xyz_m: NDArray[np.float64], heights_m: NDArray[np.float64], shape: str, voxel_m: float, min_points: int,
) -> NDArray[np.bool_]:
    """(M,) True for the cluster's voxels (M, 3) that belong to an object of ``shape`` (see the
    module doc); all True when the prior finds nothing to say."""
    keep = np.ones(len(xyz_m), dtype=bool)
    if shape == "free" or len(xyz_m) < min_points:
        return keep
    if shape == "table":
        tops = horizontal_layers(xyz_m, heights_m, voxel_m, min_points, highest_only=True)
        if not tops:
            return keep
        top = tops[0]
        keep &= heights_m <= top.height_m + TABLE_ABOVE_TOP_M
        # The outline test only for the points it decides (below the top, not the top itself).
        ask = keep & ~top.members
        keep[ask] = _near_hull(top.hull_xy_m, xyz_m[ask, :2], TABLE_OUTLINE_MARGIN_M)
        return keep
    if shape == "seat":
        # Candidates are found by their lower bin; a surface at the bounds is found from either.
        heights_band = (SEAT_MAX_HEIGHT_M - LAYER_BIN_M, FOREIGN_TOP_MAX_HEIGHT_M)
        for L in horizontal_layers(xyz_m, heights_m, voxel_m, min_points, between_m=heights_band,
                                   min_area_m2=FOREIGN_TOP_MIN_AREA_M2):
            if (SEAT_MAX_HEIGHT_M < L.height_m <= FOREIGN_TOP_MAX_HEIGHT_M and L.area_m2 >= FOREIGN_TOP_MIN_AREA_M2
                    and L.short_side_m >= FOREIGN_TOP_MIN_SHORT_M and L.fill >= FOREIGN_TOP_MIN_FILL):
                # The surface and, at its height, whatever lies at its outline (asked only of
                # the points still kept that are not the surface already).
                ask = keep & ~L.members & (np.abs(heights_m - L.height_m) <= LAYER_BIN_M)
                foreign = L.members.copy()
                foreign[ask] = _near_hull(L.hull_xy_m, xyz_m[ask, :2], 2 * voxel_m)
                keep &= ~foreign
        return keep
    raise ValueError(f"unknown shape prior {shape!r} (known: table, seat, free)")
