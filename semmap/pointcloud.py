"""Depth images to point clouds (pinhole back-projection), vectorised.

``points_camera_m`` are in the optical camera frame (x right, y down, z forward). Invalid depth
(0, NaN, inf, outside [min, max]) never becomes a point.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from semmap.frames import Transform, invert
from semmap.types import CameraIntrinsics

#: Rows of a :func:`window_points_map` table after map x, y, z (0-2): height above the plane,
#: camera z-depth, floor clearance at that depth, pixel u (then v).
HEIGHT_ROW, RANGE_ROW, CLEARANCE_ROW, PIXEL_U_ROW = 3, 4, 5, 6


def valid_depth_mask(depth_m: NDArray[np.floating], min_m: float, max_m: float) -> NDArray[np.bool_]:
    """(H, W) True where depth is finite and within [min_m, max_m] (and > 0)."""
    d = np.asarray(depth_m)
    # NaN fails every comparison and +inf fails a finite upper bound, so two comparisons
    # decide validity (this runs on every box of every frame).
    with np.errstate(invalid="ignore"):
        low = d > 0 if min_m <= 0 else d >= min_m
        high = d <= max_m if np.isfinite(max_m) else np.isfinite(d)
        return low & high


def _clipped_window(
    d: NDArray[np.floating], intrinsics: CameraIntrinsics, window_px: tuple[int, int, int, int] | None,
) -> tuple[int, int, int, int]:
    """``window_px`` = (u0, v0, u1, v1), half-open (None: the whole image), clipped to the
    depth image, which must match ``intrinsics``; empty when u1 <= u0 or v1 <= v0."""
    H, W = d.shape
    if (W, H) != (intrinsics.width_px, intrinsics.height_px):
        raise ValueError(
            f"depth image is {W}x{H} but intrinsics are for {intrinsics.width_px}x{intrinsics.height_px}"
        )
    u0, v0, u1, v1 = window_px if window_px is not None else (0, 0, W, H)
    return max(0, int(u0)), max(0, int(v0)), min(W, int(u1)), min(H, int(v1))


def project_map_points(
    points_map_m: NDArray[np.floating], intrinsics: CameraIntrinsics, T_map_camera: Transform,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Pixel coordinates u, v and camera z-depth, each (N,), of map-frame points (N, 3): the
    inverse of :func:`backproject`. Points at or behind the camera (z <= 0) are projected as
    if 1 m deep; callers mask them by z."""
    T = invert(np.asarray(T_map_camera, dtype=np.float64))
    pc = np.asarray(points_map_m, dtype=np.float64).reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
    z = pc[:, 2]
    zs = np.where(z > 0.0, z, 1.0)
    return intrinsics.fx_px * pc[:, 0] / zs + intrinsics.cx_px, intrinsics.fy_px * pc[:, 1] / zs + intrinsics.cy_px, z


def backproject(
    depth_m: NDArray[np.floating],
    intrinsics: CameraIntrinsics,
    min_m: float = 0.0,
    max_m: float = np.inf,
    window_px: tuple[int, int, int, int] | None = None,
    stride_px: int = 1,
) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
    """Back-project valid depth pixels to 3D.

    ``window_px`` = (u0, v0, u1, v1), half-open, limits the work to a box (e.g. a detection).
    ``stride_px`` subsamples rows and columns. Returns ``(points_camera_m (N, 3) float32,
    pixels_uv (N, 2) int64)``: each point with the pixel it came from.
    """
    d = np.asarray(depth_m)
    u0, v0, u1, v1 = _clipped_window(d, intrinsics, window_px)
    if u1 <= u0 or v1 <= v0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 2), np.int64)
    sub = d[v0:v1:stride_px, u0:u1:stride_px]
    ok = valid_depth_mask(sub, min_m, max_m)
    vv, uu = np.nonzero(ok)
    z = sub[vv, uu].astype(np.float32)
    # Normalised image coordinates per used column / row, then one product per axis.
    xn = ((np.arange(u0, u1, stride_px) - intrinsics.cx_px) / intrinsics.fx_px).astype(np.float32)
    yn = ((np.arange(v0, v1, stride_px) - intrinsics.cy_px) / intrinsics.fy_px).astype(np.float32)
    pts = np.empty((len(z), 3), np.float32)
    np.multiply(xn[uu], z, out=pts[:, 0])
    np.multiply(yn[vv], z, out=pts[:, 1])
    pts[:, 2] = z
    uv = np.empty((len(z), 2), np.int64)
    np.multiply(uu, stride_px, out=uv[:, 0])
    uv[:, 0] += u0
    np.multiply(vv, stride_px, out=uv[:, 1])
    uv[:, 1] += v0
    return pts, uv


def window_points_map(
    depth_m: NDArray[np.floating],
    intrinsics: CameraIntrinsics,
    min_m: float,
    max_m: float,
    window_px: tuple[int, int, int, int],
    stride_px: int,
    T_map_camera: NDArray[np.float64],
    plane_normal: NDArray[np.float64],
    plane_offset_m: float,
    clearance_m: float,
    clearance_per_m2: float,
    hole_px: tuple[int, int, int, int] | None = None,
) -> tuple[NDArray[np.float64], int]:
    """The valid pixels of a window (as :func:`backproject` samples them) in the map
    frame, keeping those higher above a plane than a range-dependent clearance.
    ``hole_px`` = (u0, v0, u1, v1), half-open: samples inside it are skipped (a ring
    around a box).

    A point is kept when its height ``plane_normal . p + plane_offset_m`` exceeds
    ``clearance_m + clearance_per_m2 * z**2`` (``z`` its camera z-depth): the floor cut of
    object geometry, whose floor points would join every leg to the room. ``T_map_camera``
    (4, 4) camera -> map, ``plane_normal`` (3,) in the map frame. Returns ``(table (8, K)
    float64, n_valid)``: rows map x, y, z (m), height above the plane, z-depth, clearance,
    pixel u, v; ``n_valid`` counts the valid pixels before the cut.

    One compiled pass (numba, cached as in :mod:`semmap.clustering`): the same numbers as
    back-projection, transform and filter done with numpy, where those took a dozen calls on a
    few thousand points per detection box.
    """
    d = np.asarray(depth_m)
    u0, v0, u1, v1 = _clipped_window(d, intrinsics, window_px)
    if u1 <= u0 or v1 <= v0:
        return np.zeros((8, 0)), 0
    T = np.asarray(T_map_camera, dtype=np.float64)
    hu0, hv0, hu1, hv1 = hole_px if hole_px is not None else (0, 0, 0, 0)
    return _window_table(
        d, u0, v0, u1, v1, int(hu0), int(hv0), int(hu1), int(hv1), int(stride_px), float(min_m), float(max_m),
        float(intrinsics.cx_px), float(intrinsics.cy_px), float(intrinsics.fx_px), float(intrinsics.fy_px),
        np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]),
        np.asarray(plane_normal, dtype=np.float64), float(plane_offset_m), float(clearance_m), float(clearance_per_m2),
    )


@numba.njit(cache=True)
def _valid_depth(z: float | np.floating[Any], min_m: float, max_m: float) -> bool:
    """:func:`valid_depth_mask` for one value."""
    low = z > 0 if min_m <= 0 else z >= min_m
    high = z <= max_m if math.isfinite(max_m) else math.isfinite(z)
    return bool(low and high)


@numba.njit(cache=True)
def _window_table(
    d: NDArray[np.floating], u0: int, v0: int, u1: int, v1: int, hu0: int, hv0: int, hu1: int, hv1: int,
    stride: int, min_m: float, max_m: float,
    cx: float, cy: float, fx: float, fy: float, R: NDArray[np.float64], t: NDArray[np.float64],
    nrm: NDArray[np.float64], off: float, clear_m: float, clear_per_m2: float,
) -> tuple[NDArray[np.float64], int]:
    """The kernel of :func:`window_points_map` (two passes: count, then fill). numba
    evaluates float32 products in float64; each is rounded back to float32, as numpy's
    float32 arrays round them (the float64 product of two float32 values is exact)."""
    n_valid, n_keep = 0, 0
    keep = np.zeros(((v1 - v0 + stride - 1) // stride) * ((u1 - u0 + stride - 1) // stride), np.bool_)
    k = 0
    for v in range(v0, v1, stride):
        yn = np.float32((v - cy) / fy)
        for u in range(u0, u1, stride):
            z = np.float32(d[v, u])
            if hv0 <= v < hv1 and hu0 <= u < hu1:
                pass  # in the hole
            elif _valid_depth(z, min_m, max_m):
                n_valid += 1
                xn = np.float32((u - cx) / fx)
                x, y, zz = np.float64(np.float32(xn * z)), np.float64(np.float32(yn * z)), np.float64(z)
                mz = R[2, 0] * x + R[2, 1] * y + R[2, 2] * zz + t[2]
                mx = R[0, 0] * x + R[0, 1] * y + R[0, 2] * zz + t[0]
                my = R[1, 0] * x + R[1, 1] * y + R[1, 2] * zz + t[1]
                h = nrm[0] * mx + nrm[1] * my + nrm[2] * mz + off
                if h > zz * zz * clear_per_m2 + clear_m:
                    keep[k] = True
                    n_keep += 1
            k += 1
    tab = np.empty((8, n_keep))
    j, k = 0, 0
    for v in range(v0, v1, stride):
        yn = np.float32((v - cy) / fy)
        for u in range(u0, u1, stride):
            if keep[k]:
                z = np.float32(d[v, u])
                xn = np.float32((u - cx) / fx)
                x, y, zz = np.float64(np.float32(xn * z)), np.float64(np.float32(yn * z)), np.float64(z)
                mx = R[0, 0] * x + R[0, 1] * y + R[0, 2] * zz + t[0]
                my = R[1, 0] * x + R[1, 1] * y + R[1, 2] * zz + t[1]
                mz = R[2, 0] * x + R[2, 1] * y + R[2, 2] * zz + t[2]
                tab[0, j], tab[1, j], tab[2, j] = mx, my, mz
                tab[3, j] = nrm[0] * mx + nrm[1] * my + nrm[2] * mz + off
                tab[4, j] = zz
                tab[5, j] = zz * zz * clear_per_m2 + clear_m
                tab[6, j], tab[7, j] = u, v
                j += 1
            k += 1
    return tab, n_valid
