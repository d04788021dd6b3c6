"""The wall behind an object: found on the pixels around its box, and cut away with what lies beyond.

An object a few centimetres in front of a wall clusters together with it. A wall is a vertical
plane (a line in the map plane) fitted on a ring of pixels just outside the box
(:func:`background_walls`), accepted only when nothing of the ring stands behind it and it
faces the camera; :func:`in_front_of_walls` keeps the box's points in front of such walls,
unless the box's own points stand behind one (then it is an occluder in front of the object).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray

from semmap.config import GeometryConfig
from semmap.frames import Transform
from semmap.pointcloud import RANGE_ROW, window_points_map
from semmap.ransac import Plane
from semmap.types import CameraIntrinsics

__all__ = ["background_walls", "in_front_of_walls", "noise_tolerance_m"]

#: Background walls are fitted on a ring of pixels around the box: this far outside it (box
#: jitter must not put the object's own edge in the ring), this wide, sampled at this stride.
_RING_GAP_PX = 4
_RING_WIDTH_PX = 12
_RING_STRIDE_PX = 4
#: A wall is a vertical plane holding at least this share of the ring's above-floor points
#: (and ``_WALL_MIN_POINTS``), with at most ``_WALL_MAX_BEHIND`` of them beyond it.
_WALL_MIN_SHARE = 0.15
_WALL_MIN_POINTS = 30
_WALL_MAX_BEHIND = 0.1
_WALL_HYPOTHESES = 64
#: A wall faces the camera: cosine between its normal and the line of sight at least this.
_WALL_MIN_FACING = 0.35


def _ring_windows(
    xyxy_px: tuple[float, float, float, float], width_px: int, height_px: int,
) -> tuple[tuple[int, int, int, int], tuple[int, int, int, int]]:
    """The ring of pixels just outside a box, for finding the wall behind the object: its
    outer window (u0, v0, u1, v1), clipped to the image, and the hole in it (the box grown by
    the gap), both half-open, the hole on the ring's sample grid (``_RING_STRIDE_PX``)."""
    u0, v0, u1, v1 = xyxy_px
    g, w, s = _RING_GAP_PX, _RING_GAP_PX + _RING_WIDTH_PX, _RING_STRIDE_PX
    ou0, ov0 = max(0, int(u0) - w), max(0, int(v0) - w)
    ou1, ov1 = min(width_px, int(math.ceil(u1)) + w), min(height_px, int(math.ceil(v1)) + w)
    # First and last-but-one sample index inside the grown box, per axis.
    r0, r1 = -(-(int(v0) - g - ov0) // s), -(-(int(math.ceil(v1)) + g - ov0) // s)
    c0, c1 = -(-(int(u0) - g - ou0) // s), -(-(int(math.ceil(u1)) + g - ou0) // s)
    hole = (ou0 + s * max(0, c0), ov0 + s * max(0, r0), ou0 + s * max(0, c1), ov0 + s * max(0, r1))
    return (ou0, ov0, ou1, ov1), hole


def noise_tolerance_m(range_m: NDArray[np.float64], params: GeometryConfig) -> NDArray[np.float64]:
    """(N,) distance within which a point at ``range_m`` (N,) counts as on a surface: the RANSAC
    distance plus half the floor cut's range-squared term (depth noise grows with range^2)."""
    return params.ransac_distance_m + 0.5 * params.floor_clearance_per_m2 * range_m**2



@numba.njit(cache=True)
def _fit_wall(
    xy: NDArray[np.float64], tol: NDArray[np.float64], remaining: NDArray[np.bool_], pairs: NDArray[np.int64],
    min_support: float, cam_x: float, cam_y: float, max_behind: float, min_facing: float,
    out_inliers: NDArray[np.bool_],
) -> tuple[bool, float, float, float]:
    """One wall search of :func:`background_walls`, compiled (numba, cached as in
    :mod:`semmap.clustering`): ``(found, normal x, normal y, offset)``, the wall's points
    written to ``out_inliers`` (N,).

    ``xy`` (N, 2) above-floor ring points with tolerances ``tol`` (N,); ``pairs`` (Hy, 2) the
    drawn point pairs, each a line hypothesis (pairs closer than 5 cm are none). The line with
    most ``remaining`` points within their tolerance wins (first of equals) and is refitted by
    least squares (the major axis of its points' 2x2 scatter), its normal turned towards the
    camera. It is a wall with at least ``min_support`` remaining points on it, at most
    ``max_behind`` of all points beyond it, and seen at least ``min_facing`` (cosine) face-on.
    """
    n_all = xy.shape[0]
    best, best_support, best_nx, best_ny, best_off = _most_supported_line(xy, tol, remaining, pairs)
    if best < 0 or best_support < min_support:
        return False, 0.0, 0.0, 0.0
    cx, cy, nx, ny, off = _refit_line(xy, tol, remaining, best_nx, best_ny, best_off)
    if nx * cam_x + ny * cam_y + off < 0:
        nx, ny, off = -nx, -ny, -off
    n_in, n_behind = 0, 0
    for k in range(n_all):
        dist = xy[k, 0] * nx + xy[k, 1] * ny + off
        out_inliers[k] = remaining[k] and abs(dist) <= tol[k]
        if out_inliers[k]:
            n_in += 1
        if dist < -tol[k]:
            n_behind += 1
    if n_in < min_support:
        return False, 0.0, 0.0, 0.0
    if n_behind / n_all > max_behind:
        return False, 0.0, 0.0, 0.0  # things stand behind it: a piece of furniture, not the room's boundary
    vx, vy = cx - cam_x, cy - cam_y
    if abs(nx * vx + ny * vy) < min_facing * math.hypot(vx, vy):
        return False, 0.0, 0.0, 0.0  # seen edge-on: a strip of something along the line of sight
    return True, nx, ny, off


@numba.njit(cache=True)
def _most_supported_line(
    xy: NDArray[np.float64], tol: NDArray[np.float64], remaining: NDArray[np.bool_], pairs: NDArray[np.int64],
) -> tuple[int, int, float, float, float]:
    """The pair hypothesis with the most ``remaining`` points within their tolerance (first
    of equals): ``(index, support, normal x, normal y, offset)``, index -1 when none."""
    best, best_support = -1, -1
    best_nx, best_ny, best_off = 0.0, 0.0, 0.0
    for hyp in range(pairs.shape[0]):
        i, j = pairs[hyp, 0], pairs[hyp, 1]
        dx, dy = xy[j, 0] - xy[i, 0], xy[j, 1] - xy[i, 1]
        length = math.hypot(dx, dy)
        if length <= 0.05:
            continue
        nx, ny = -dy / length, dx / length
        off = -(nx * xy[i, 0] + ny * xy[i, 1])
        support = 0
        for k in range(xy.shape[0]):
            if remaining[k] and abs(xy[k, 0] * nx + xy[k, 1] * ny + off) <= tol[k]:
                support += 1
        if support > best_support:
            best, best_support = hyp, support
            best_nx, best_ny, best_off = nx, ny, off
    return best, best_support, best_nx, best_ny, best_off


@numba.njit(cache=True)
def _refit_line(
    xy: NDArray[np.float64], tol: NDArray[np.float64], remaining: NDArray[np.bool_],
    nx: float, ny: float, off: float,
) -> tuple[float, float, float, float, float]:
    """Least squares on the line's ``remaining`` points (centroid, then the scatter's major
    axis): ``(centroid x, centroid y, normal x, normal y, offset)``."""
    n_all = xy.shape[0]
    sx, sy, m = 0.0, 0.0, 0
    for k in range(n_all):
        if remaining[k] and abs(xy[k, 0] * nx + xy[k, 1] * ny + off) <= tol[k]:
            sx += xy[k, 0]
            sy += xy[k, 1]
            m += 1
    cx, cy = sx / m, sy / m
    sxx, sxy, syy = 0.0, 0.0, 0.0
    for k in range(n_all):
        if remaining[k] and abs(xy[k, 0] * nx + xy[k, 1] * ny + off) <= tol[k]:
            ex, ey = xy[k, 0] - cx, xy[k, 1] - cy
            sxx += ex * ex
            sxy += ex * ey
            syy += ey * ey
    theta = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
    rnx, rny = -math.sin(theta), math.cos(theta)
    return cx, cy, rnx, rny, -(rnx * cx + rny * cy)

def background_walls(
    ring_xy_m: NDArray[np.float64], ring_range_m: NDArray[np.float64], camera_xy_m: NDArray[np.float64],
    params: GeometryConfig, rng: np.random.Generator,
) -> list[tuple[NDArray[np.float64], float]]:
    """Vertical planes (walls) behind an object, from the points around its box.

    ``ring_xy_m``: (N, 2) map-plane positions of the pixels around the box that lie above
    the floor cut, ``ring_range_m`` (N,) their camera z-depths, ``camera_xy_m`` (2,). A wall
    is a vertical plane (a line in the map plane) holding a large share of those points with
    almost none beyond it: the room's boundary, which nothing stands behind. Returns up to
    two walls (a corner) as ``(normal_xy (2,), offset_m)`` with the normal towards the
    camera, so ``normal . xy + offset`` is the distance in front of the wall.
    """
    xy = np.ascontiguousarray(ring_xy_m, dtype=np.float64).reshape(-1, 2)
    n_all = len(xy)
    if n_all < _WALL_MIN_POINTS:
        return []
    tol = noise_tolerance_m(np.asarray(ring_range_m, dtype=np.float64), params)  # (N,)
    remaining = np.ones(n_all, dtype=bool)
    walls: list[tuple[NDArray[np.float64], float]] = []
    cam_x, cam_y = float(camera_xy_m[0]), float(camera_xy_m[1])
    for share in (_WALL_MIN_SHARE, _WALL_MIN_SHARE / 2):
        idx = np.nonzero(remaining)[0]
        if len(idx) < _WALL_MIN_POINTS:
            break
        pairs = idx[rng.integers(0, len(idx), size=(_WALL_HYPOTHESES, 2))]
        inl = np.empty(n_all, dtype=bool)
        found, nx, ny, off = _fit_wall(xy, tol, remaining, pairs, float(max(_WALL_MIN_POINTS, share * n_all)),
                                       cam_x, cam_y, _WALL_MAX_BEHIND, _WALL_MIN_FACING, inl)
        if not found:
            break
        walls.append((np.array([nx, ny]), off))
        remaining &= ~inl
    return walls


def in_front_of_walls(
    tab: NDArray[np.float64], depth_m: NDArray[np.floating], intrinsics: CameraIntrinsics, T_map_camera: Transform,
    xyxy_px: tuple[float, float, float, float], params: GeometryConfig, floor: Plane,
    depth_range_m: tuple[float, float], rng: np.random.Generator,
) -> NDArray[np.bool_] | None:
    """(N,) which of a box's points (``tab``, a ``window_points_map`` table (8, N)) lie in front
    of the walls behind the box ``xyxy_px``; None when no wall was found behind it."""
    H, W = np.asarray(depth_m).shape
    # The ring's valid pixels (n_ring) and, as a table like the box's, those above the floor
    # cut: what the wall is fitted on.
    outer, hole = _ring_windows(xyxy_px, W, H)
    ring_tab, n_ring = window_points_map(
        depth_m, intrinsics, depth_range_m[0], depth_range_m[1], outer, _RING_STRIDE_PX, T_map_camera,
        floor.normal_array, floor.offset_m, params.floor_clearance_m, params.floor_clearance_per_m2,
        hole_px=hole,
    )
    if n_ring < _WALL_MIN_POINTS:
        return None
    walls = background_walls(ring_tab[:2].T, ring_tab[RANGE_ROW], T_map_camera[:2, 3], params, rng)
    if not walls:
        return None
    tol = noise_tolerance_m(tab[RANGE_ROW], params)
    front = np.ones(tab.shape[1], dtype=bool)
    for n_xy, off in walls:
        dist = n_xy @ tab[:2] + off  # (N,) in front of the wall
        # Nothing of the box stands behind a wall; a "wall" with the box's points behind it is
        # an occluder in front of the object.
        if np.count_nonzero(dist < -tol) <= _WALL_MAX_BEHIND * len(dist):
            front &= dist > tol
    return front
